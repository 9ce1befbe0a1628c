"""The energyctl subcommands, one module each: ``add_parser(subparsers)`` declares its options (and sets
``func=run``), ``run(args) -> int`` does it and returns the exit code."""

from __future__ import annotations

from clients.commands import (
    bench,
    compare,
    coordinator,
    demo,
    foxglove,
    load,
    log,
    plant,
    query,
    replay,
    report,
    router,
    run,
    schema,
    secure_profile,
    sim,
    sweep,
)

# in the order energyctl --help lists them
COMMANDS = (sim, compare, sweep, demo, bench, run, plant, coordinator, load, query, router, secure_profile, replay,
            log, report, schema, foxglove)
