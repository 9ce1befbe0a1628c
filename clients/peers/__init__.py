"""Zenoh peers that stand in for the rest of the system: the hardware-in-the-loop plant (``energyctl plant``,
:mod:`clients.peers.plant`) and the neighbour load (``energyctl load``, :mod:`clients.peers.load`)."""
