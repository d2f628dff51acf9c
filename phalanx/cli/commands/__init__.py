"""CLI command groups; each module's `register(app)` adds its commands.

Modules here keep heavy imports (zenoh, rerun, can, serial) inside the command bodies so
that `phalanx --help` stays fast.
"""
