"""The bottom layer: types and math every other layer may use, and nothing else.

Errors, geometry, configuration models and files, the formation's shape and the exact
rigid-body motion of its slots, kinematic limits, what a robot reports, behaviour state
names, a run's log, generated scenarios. No I/O beyond reading configuration files.
"""
