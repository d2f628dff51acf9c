"""Rerun telemetry: the stream every process logs to, its layout (the blueprint and the
columns it sends), and reading recordings back.
"""
