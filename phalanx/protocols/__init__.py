"""Byte-level codecs of the robots' own protocols (ARCOS, CiA 402), pure functions.

Both sides need them: the drivers (`phalanx.drivers`) speak them to a robot, and the
simulated robots (`phalanx.simulator`) answer them. They sit below both, so drivers and
simulator never import each other.
"""
