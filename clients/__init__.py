"""Clients: the energyctl CLI (cli.py assembling commands/, shared options in options.py), the hardware-in-the-loop
plant and neighbour load stand-ins (peers/), the query client, process orchestration for demos (live.py), the secure
profile, log tools, the report, and the benches (bench/)."""
