"""docs/SWEEPS.md's configuration file for workers started by hand gives them the same
settings as `phalanx sweep`'s own local workers (`QUIET_DASK`, and glibc's threshold
for handing memory back kept rather than the nanny's). A real `dask worker` reading the
file is checked in tests/integration/test_sweep_cluster.py.
"""

from __future__ import annotations

from typing import Any

import yaml
from dask_cluster import worker_config_file

from phalanx.analysis.sweep import QUIET_DASK


def _flat(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and key != "pre-spawn-environ":
            out.update(_flat(value, f"{name}."))
        else:
            out[name] = value
    return out


def test_the_worker_file_in_the_docs_has_the_sweeps_settings() -> None:
    settings = _flat(yaml.safe_load(worker_config_file()))
    environ = settings.pop("distributed.nanny.pre-spawn-environ")
    assert settings == QUIET_DASK
    assert environ["MALLOC_TRIM_THRESHOLD_"] > 65536  # (the nanny's: every free handed back)
