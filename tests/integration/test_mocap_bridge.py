"""`phalanx mocap` against the motioncapture library's mock backend: its rigid bodies
arrive as pose fixes on each robot's `fix` key, in the world frame, with the scenario's
noise figures, over real Zenoh on loopback."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import pytest

from phalanx.core.config_files import CONFIG_ROOT
from phalanx.wire.keys import robots_key
from phalanx.wire.positions import PoseFixMessage
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint, open_session

pytest.importorskip("motioncapture", reason="the mocap bridge needs the sensing extra")
pytestmark = pytest.mark.integration
SCENARIO = CONFIG_ROOT / "scenarios" / "real_wedge.toml"
# r1 at (1, 2) facing +90 deg; "p3dx_3" is r3 under another name; "cup" is nobody's
BODIES = "r1(1.0,2.0,0.3,0.7071068,0,0,0.7071068);p3dx_3(-0.5,0.25,0.3,1,0,0,0);cup(0,0,0,1,0,0,0)"


def test_rigid_bodies_become_pose_fixes() -> None:
    endpoint = loopback_endpoint(free_tcp_port())
    got: list[PoseFixMessage] = []
    lock = threading.Lock()

    def keep(_key: str, message: PoseFixMessage) -> None:
        with lock:
            got.append(message)

    config = TransportConfig(mode="peer", listen=(endpoint,))
    with open_session(config) as session:
        session.subscribe(robots_key("mocaptest", "fix"), PoseFixMessage, keep)
        started = time.time()
        proc = subprocess.run(
            [sys.executable, "-m", "phalanx", "mocap", str(SCENARIO), "--system", "mock",
             "--setting", f"rigid_bodies={BODIES}", "--body", "p3dx_3=r3",
             "--origin", "10,0,90", "--fleet", "mocaptest", "--connect", endpoint,
             "--duration", "2"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        time.sleep(0.2)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with lock:
        fixes = {m.robot_id: m for m in got}
    assert set(fixes) == {"r1", "r3"}
    assert len(got) > 50  # the mock runs at 100 Hz for 2 s, both bodies
    r1, r3 = fixes["r1"], fixes["r3"]
    # the mocap frame sits at (10, 0) turned 90 deg in the world
    assert (r1.x_m, r1.y_m, abs(r1.theta_rad)) == pytest.approx((8.0, 1.0, math.pi), abs=1e-5)
    assert (r3.x_m, r3.y_m, r3.theta_rad) == pytest.approx((9.75, -0.5, math.pi / 2), abs=1e-5)
    assert r1.std_m == pytest.approx(0.002)
    assert r1.std_rad == pytest.approx(math.radians(0.1))
    assert started - 1.0 < r1.stamp_s < time.time()
    assert "unmapped" in proc.stderr
