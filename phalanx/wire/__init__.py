"""What crosses the network between phalanx processes: the versioned messages, their
encoding, every Zenoh key, and the session wrapper that publishes and subscribes.
"""
