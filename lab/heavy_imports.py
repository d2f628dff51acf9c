"""The libraries a `phalanx` command should import only when its work needs them: what
`tests/unit/test_lazy_imports.py` holds the commands to and `bench/bench_startup.py`
reports a command importing.
"""

# What a command's work needs, and nothing before it: plotting, recording, certificates,
# a cluster, the middleware, ROS bags, SciPy.
WORK_LIBRARIES = (
    "matplotlib",
    "rerun",
    "cryptography",
    "dask",
    "distributed",
    "zenoh",
    "rosbags",
    "scipy",
)
# Also left out of the import and the top-level help: arrays, models, rich text.
HEAVY = (*WORK_LIBRARIES, "numpy", "pydantic", "rich")
