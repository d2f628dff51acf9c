"""A fleet over many machines: deployment files, the per-host daemon and its protocol,
and the client behind `phalanx launch`, `status` and `stop`.
"""
