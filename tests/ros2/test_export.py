"""A run exported to a rosbag2 MCAP bag, read back by two readers that are not ours: the
MCAP library's reader with its ROS 2 decoder (mcap-ros2-support, what Foxglove's stack
uses) and rosbags' rosbag2 reader with its CDR deserialiser. Topics, types, message
counts, log times and values are checked against the run's own traces, message for
message; `phalanx run --mcap` writes the same bag as `phalanx export` of its folder.
"""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from phalanx.analysis.metrics import run_metrics
from phalanx.analysis.results import read_traces, write_metrics, write_traces
from phalanx.cli import app
from phalanx.core.config import Scenario
from phalanx.runtime.batch import run_batch

from .conftest import WEDGE

DURATION_S = 20.0
ROBOTS = ("r1", "r2", "r3")
TYPES = {
    **{f"/{r}/odom": "nav_msgs/msg/Odometry" for r in ROBOTS},
    **{f"/{r}/cmd_vel_out": "geometry_msgs/msg/Twist" for r in ROBOTS},
    **{f"/{r}/state": "std_msgs/msg/String" for r in ROBOTS},
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/markers": "visualization_msgs/msg/MarkerArray",
}


@pytest.fixture(scope="module")
def results(wedge: Scenario, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 20 s paper wedge's results folder (metrics.json, traces.npz) and its bag."""
    folder = tmp_path_factory.mktemp("wedge")
    log = run_batch(wedge.model_copy(update={"duration_s": DURATION_S}))
    write_metrics(run_metrics(log), folder / "metrics.json")
    write_traces(log, folder / "traces.npz")
    args = ["export", str(folder), "--mcap", "--scenario", str(WEDGE)]
    result = CliRunner().invoke(app, args, prog_name="phalanx")
    assert result.exit_code == 0, result.output
    return folder


def _mcap_messages(bag: Path) -> list[tuple[str, str, int, Any]]:
    """(topic, schema, log time ns, decoded) of every message, by the MCAP library."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (path,) = bag.glob("*.mcap")
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return [
            (channel.topic, schema.name, message.log_time, decoded)
            for schema, channel, message, decoded in reader.iter_decoded_messages()
        ]


def test_the_mcap_librarys_decoder_reads_every_message_of_the_run(results: Path) -> None:
    traces = read_traces(results / "traces.npz")
    t_ns = np.round(traces[""]["t_s"] * 1e9).astype(np.int64)
    steps = len(t_ns)
    messages = _mcap_messages(results / "rosbag2")
    assert {topic: schema for topic, schema, _, _ in messages} == TYPES
    counts = Counter(topic for topic, *_ in messages)
    for rid in ROBOTS:
        states = list(traces[rid]["state"])
        changes = 1 + sum(a != b for a, b in pairwise(states))
        assert (counts[f"/{rid}/odom"], counts[f"/{rid}/cmd_vel_out"]) == (steps, steps)
        assert counts[f"/{rid}/state"] == changes
        said = [d.data for topic, _, _, d in messages if topic == f"/{rid}/state"]
        assert said == [s for k, s in enumerate(states) if k == 0 or s != states[k - 1]]
    assert counts["/tf"] == steps
    assert counts["/tf_static"] == 1
    assert counts["/markers"] == round(DURATION_S)  # once a second of run time
    for rid in ROBOTS:
        odom = [(t, d) for topic, _, t, d in messages if topic == f"/{rid}/odom"]
        assert [t for t, _ in odom] == t_ns.tolist()
        stamps = [d.header.stamp.sec * 10**9 + d.header.stamp.nanosec for _, d in odom]
        assert stamps == t_ns.tolist()
        x = [d.pose.pose.position.x for _, d in odom]
        np.testing.assert_array_equal(x, traces[rid]["x_m"])
        v = [d.twist.twist.linear.x for _, d in odom]
        np.testing.assert_array_equal(v, traces[rid]["v_mps"])
        cmd = [d.angular.z for topic, _, _, d in messages if topic == f"/{rid}/cmd_vel_out"]
        np.testing.assert_array_equal(cmd, traces[rid]["cmd_omega_radps"])


def test_rosbags_reader_sees_the_same_bag(results: Path) -> None:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    traces = read_traces(results / "traces.npz")
    t_s = traces[""]["t_s"]
    with Reader(results / "rosbag2") as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TYPES
        assert reader.start_time == 0
        assert reader.duration == round(t_s[-1] * 1e9) + 1  # rosbag2: end - start + 1 ns
        assert {c.digest for c in reader.connections if c.topic == "/r2/odom"} == {
            store.hash_rihs01("nav_msgs/msg/Odometry")
        }
        tf = [c for c in reader.connections if c.topic == "/tf"]
        poses = [
            store.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage")
            for _, _, raw in reader.messages(connections=tf)
        ]
        static = [c for c in reader.connections if c.topic == "/tf_static"]
        (mounts,) = [store.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(static)]
    assert len(poses) == len(t_s)
    last = {t.child_frame_id: t.transform.translation for t in poses[-1].transforms}
    assert last["r3/base_link"].y == traces["r3"]["y_m"][-1]
    assert len(mounts.transforms) == 3 * 16


def test_run_with_mcap_writes_the_bag_export_writes(results: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    args = ["run", str(WEDGE), "--out", str(out), "--set", f"duration_s={DURATION_S}",
            "--no-recording", "--no-figures", "--no-progress", "--mcap"]  # fmt: skip
    result = CliRunner().invoke(app, args, prog_name="phalanx")
    assert result.exit_code == 0, result.output
    ran = [(t, s, n) for t, s, n, _ in _mcap_messages(out / "rosbag2")]
    exported = [(t, s, n) for t, s, n, _ in _mcap_messages(results / "rosbag2")]
    assert ran == exported
    assert (out / "rosbag2" / "metadata.yaml").read_text() == (
        results / "rosbag2" / "metadata.yaml"
    ).read_text()


def test_a_folder_without_traces_is_refused_with_the_way_out(tmp_path: Path) -> None:
    (tmp_path / "metrics.json").write_text("{}")
    result = CliRunner().invoke(app, ["export", str(tmp_path), "--mcap"], prog_name="phalanx")
    assert result.exit_code != 0
    assert "no traces.npz" in str(result.exception)
    assert not (tmp_path / "rosbag2").exists()


def _spoilt(name: str, good: Path, out: Path) -> None:
    """`good`'s traces, spoilt as `name` says, written to `out`."""
    raw = good.read_bytes()
    if name in ("cut short", "empty"):
        out.write_bytes(raw[:300] if name == "cut short" else b"")
        return
    with np.load(good) as data:
        arrays = {key: data[key] for key in data.files}
    if name == "a position past the world":
        arrays["r2/x_m"][3] = 1e308
    elif name == "step times of inf":
        arrays["t_s"] = np.full_like(arrays["t_s"], np.inf)
    elif name == "a robot not there yet":
        arrays["r2/x_m"][:3] = np.nan
    np.savez(out, **arrays)


@pytest.mark.parametrize(
    ("name", "says"),
    [
        ("cut short", "not a numpy archive"),
        ("empty", "not a numpy archive"),
        ("a position past the world", "r2/x_m: values beyond +-1e+06"),
        ("step times of inf", "step times must lie from 0 to 86400 s"),
    ],
)
def test_a_spoilt_traces_file_is_refused_with_what_is_wrong(
    results: Path, tmp_path: Path, name: str, says: str
) -> None:
    # Before, these ended in a traceback (zipfile's BadZipFile; an OverflowError at step
    # times of inf), in click's bare "Aborted!" (numpy's EOFError on an empty file), or
    # in a bag with a robot 1e308 m off.
    (tmp_path / "metrics.json").write_text("{}")
    _spoilt(name, results / "traces.npz", tmp_path / "traces.npz")
    result = CliRunner().invoke(app, ["export", str(tmp_path), "--mcap"], prog_name="phalanx")
    assert result.exit_code != 0
    assert "not a run's traces" in str(result.exception)
    assert says in str(result.exception)
    assert not (tmp_path / "rosbag2").exists()


def test_a_robot_not_there_yet_is_exported(results: Path, tmp_path: Path) -> None:
    _spoilt("a robot not there yet", results / "traces.npz", tmp_path / "traces.npz")
    result = CliRunner().invoke(app, ["export", str(tmp_path), "--mcap"], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "rosbag2" / "metadata.yaml").exists()


def test_an_archive_that_unpacks_to_more_than_a_run_writes_is_not_read(
    results: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # (the bound made small: a real bomb of 2.4 GB unpacked is 2.3 MB packed, slow to make)
    import phalanx.analysis.results as results_module

    size = sum(np.load(results / "traces.npz")[k].nbytes for k in ("t_s", "r1/x_m"))
    monkeypatch.setattr(results_module, "MAX_TRACES_BYTES", size)
    with pytest.raises(ValueError, match="more than any run writes"):
        read_traces(results / "traces.npz")


def test_phalanx_imports_and_loads_scenarios_without_rosbags() -> None:
    # What is off costs nothing: no ROS 2 library is imported by phalanx, its CLI or a
    # scenario; asked for, the bridge says how to install it.
    code = (
        "import sys; sys.modules['rosbags'] = None\n"
        "import phalanx.cli, phalanx.ros2.bridge, phalanx.ros2.export\n"
        "from phalanx.core.config_files import load_scenario\n"
        f"load_scenario({str(WEDGE)!r})\n"
        "from phalanx.core.errors import ConfigError\n"
        "from phalanx.ros2.typestore import store\n"
        "try:\n    store()\nexcept ConfigError as exc:\n    print(exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "pip install 'phalanx[ros2]'" in out.stdout
