"""The network wing: the pure interconnection layer (``layer``), the network's offline closed loop (``netsim``), the
rig's model of the network plant side (``netrig``) and the replay of a coordinator's log (``layer_replay``). The
coordinator that runs the layer live is a runtime service (``service.daemon.coordinator``)."""
