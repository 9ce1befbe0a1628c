"""Clients: hardware-in-the-loop plant, neighbour load, query client, replay, and the energyctl CLI."""
