"""Running the brain: the in-process batch runner, the agent process (one runtime built
from a clock and a robot I/O), the world process, and `phalanx up` (a whole fleet as
processes on this machine).
"""
