"""The benches of ``energyctl bench`` and the rigs they run: one module per bench (sim, core, tick and replay,
latency, recorder, realtime, soak, recovery with its fault-injection Rig, wake, middleware)."""
