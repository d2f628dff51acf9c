"""Config files: TOML (or JSON) into the models of `phalanx.core.config`, and overrides.

`load_scenario` and `load_robot` turn validation errors into a `ConfigError` that names
the file, the field path and, for a misspelt key, the closest valid name;
`apply_overrides` applies dotted `path=value` assignments to a scenario and validates the
result again.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from phalanx.core.config import Scenario, check_robot_file
from phalanx.core.errors import ConfigError
from phalanx.core.formation import scenario_formation
from phalanx.core.mapfile import GridMap, load_map
from phalanx.core.robot_params import RobotParams

CONFIG_ROOT = Path(__file__).resolve().parents[2] / "configs"
ROBOTS_DIR = CONFIG_ROOT / "robots"
# A scenario of MAX_ROBOTS robots is about 100 kB of TOML; anything much bigger is not one.
MAX_FILE_BYTES = 4 * 1024 * 1024
# Tables and arrays in tables and arrays: the deepest file in configs/ nests 6 levels;
# past this a file is not a configuration (and a parser's recursion would run out).
MAX_DEPTH = 32
_TOO_DEEP = f"nested too deeply: tables or arrays more than {MAX_DEPTH} levels deep"

M = TypeVar("M", bound=BaseModel)


def _field_names(model: type[BaseModel], loc: tuple[int | str, ...]) -> list[str]:
    """Valid field names at the parent of an error location, for "did you mean"."""
    current: Any = model
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        fields = getattr(current, "model_fields", {})
        if part not in fields:
            return []
        annotation = fields[part].annotation
        current = _innermost_model(annotation)
        if current is None:
            return []
    return list(getattr(current, "model_fields", {}))


def _innermost_model(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = _innermost_model(arg)
        if found is not None:
            return found
    return None


def _describe(error: Mapping[str, Any], model: type[BaseModel]) -> str:
    loc = tuple(error["loc"])
    path = ".".join(str(p) for p in loc) or "<root>"
    message = f"{path}: {error['msg']}"
    if error["type"] == "extra_forbidden" and loc:
        hints = difflib.get_close_matches(str(loc[-1]), _field_names(model, loc), n=1)
        if hints:
            message += f" (did you mean {hints[0]!r}?)"
    return message


def validate_file(model: type[M], path: Path) -> M:
    """Read a TOML file (or JSON, as tools write it) into `model`.

    Raises ConfigError naming the file, the field path and a hint.
    """
    text = read_text(path)
    try:
        data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except RecursionError as exc:
        raise ConfigError(f"{path}: {_TOO_DEEP}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table at the top level")
    return validate_data(model, data, source=str(path))


def read_text(path: Path, *, limit: int = MAX_FILE_BYTES) -> str:
    """A configuration file's text, or ConfigError saying why it cannot be one."""
    try:
        with path.open("rb") as handle:
            raw = handle.read(limit + 1)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such file") from exc
    except IsADirectoryError as exc:
        raise ConfigError(f"{path}: is a directory, not a file") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read: {exc.strerror or exc}") from exc
    except ValueError as exc:  # a NUL in the path
        raise ConfigError(f"{str(path)!r}: not a file's path: {exc}") from exc
    if len(raw) > limit:
        raise ConfigError(
            f"{path}: larger than {limit // (1024 * 1024)} MiB: not a configuration file"
        )
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not a text file (byte {exc.start} is not UTF-8): give a TOML file"
        ) from exc


def validate_data(model: type[M], data: Mapping[str, Any], *, source: str) -> M:
    """Validate a mapping into `model`, or raise ConfigError naming source and fields."""
    if _deeper_than(data, MAX_DEPTH):
        raise ConfigError(f"{source}: {_TOO_DEEP}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        lines = [_describe(e, model) for e in exc.errors()]
        raise ConfigError(f"{source}: invalid {model.__name__}:\n  " + "\n  ".join(lines)) from exc


def _deeper_than(data: Any, limit: int) -> bool:
    """Whether tables and arrays in `data` nest more than `limit` levels (no recursion)."""
    stack: list[tuple[Any, int]] = [(data, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > limit:
            return True
        if isinstance(node, Mapping):
            stack += [(child, depth + 1) for child in node.values()]
        elif isinstance(node, list | tuple):
            stack += [(child, depth + 1) for child in node]
    return False


def robot_file(name_or_path: str | Path) -> Path:
    """The robot parameter file a scenario's `robot` names: a robot's name is the file
    `configs/robots/NAME.toml`, a path with its own `.toml` extension is that file; any
    other value (`/etc/passwd`) is a ConfigError.
    """
    try:
        check_robot_file(str(name_or_path))
    except ValueError as exc:
        raise ConfigError(f"robot: {exc}") from None
    path = Path(name_or_path)
    return path if path.suffix == ".toml" else ROBOTS_DIR / f"{path}.toml"


def load_robot(name_or_path: str | Path) -> RobotParams:
    """Load a robot parameter file by name (configs/robots/NAME.toml) or by a path of
    its own `.toml` file (`robot_file`).
    """
    return validate_file(RobotParams, robot_file(name_or_path))


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario file (TOML; JSON is accepted for generated scenarios); its
    formation is resolved too, so a follow cycle is reported here, naming the file.
    """
    try:
        scenario = validate_file(Scenario, Path(path))
    except ConfigError as exc:
        if _is_robot_file(Path(path)):
            raise ConfigError(
                f"{path}: this is a robot file (one robot model's parameters, as in "
                "configs/robots/), not a scenario: give a scenario file (as in "
                'configs/scenarios/), which names its robot with robot = "p3dx"'
            ) from exc
        raise
    check_formation(scenario, source=str(path))
    return scenario


def _is_robot_file(path: Path) -> bool:
    """Whether a file that is not a valid scenario holds a robot's parameters instead:
    a TOML table whose keys are all robot fields (more than its `name`).
    """
    try:
        data = tomllib.loads(read_text(path))
    except (ConfigError, tomllib.TOMLDecodeError, RecursionError):
        return False
    return holds_robot_params(data)


def holds_robot_params(data: object) -> bool:
    """Whether a file's top-level table holds a robot's parameters: all its keys robot
    fields, more than its `name`.
    """
    if not isinstance(data, dict):
        return False
    keys = set(data) - {"name"}
    return bool(keys) and keys <= set(RobotParams.model_fields)


def check_formation(scenario: Scenario, *, source: str) -> None:
    """ConfigError naming `source` if the scenario's formation cannot be resolved."""
    try:
        scenario_formation(scenario)
    except ConfigError as exc:
        raise ConfigError(
            f"{source}: {exc} (every slot must follow, through `follows`, the one slot "
            "that follows nobody)"
        ) from exc


def apply_overrides(
    scenario: Scenario, assignments: list[str], *, source: str | None = None
) -> Scenario:
    """A copy of `scenario` with dotted `path=value` assignments (TOML values) applied.

    For example `controller.kind="ours"` or `noise.sonar_std_m=0.02`; bare words are taken
    as strings, so `controller.kind=ours` works too. The result is validated again.
    Errors name `source` (the scenario's file) and the `--set` value at fault.
    """
    where = source or scenario.name
    data = scenario.model_dump(mode="python")
    for assignment in assignments:
        try:
            path, value = parse_assignment(assignment)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        _set_path(data, path.split("."), value, assignment, where)
    label = f"{where} with --set {' '.join(assignments)}"
    result = validate_data(Scenario, data, source=label)
    check_formation(result, source=label)
    return result


def parse_assignment(text: str) -> tuple[str, Any]:
    """A `--set PATH=VALUE` assignment as its stripped dotted path and its value, read as
    `parse_value` reads it; a `ConfigError` if there is no `=` or no path before it.
    """
    path, sep, value = text.partition("=")
    if not sep or not path.strip():
        raise ConfigError(f"--set {text!r}: expected PATH=VALUE, e.g. duration_s=60")
    try:
        return path.strip(), parse_value(value.strip())
    except ConfigError as exc:
        raise ConfigError(f"--set {path.strip()}: {exc}") from None


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def parse_value(text: str) -> Any:
    """A command-line value as TOML reads it (`0.3`, `true`, `"x"`, `[1, 2]`); anything
    TOML cannot read is taken as a bare string.
    """
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except RecursionError as exc:
        raise ConfigError(f"value {text[:40]!r}: {_TOO_DEEP}") from exc
    except tomllib.TOMLDecodeError:
        return text


def _set_path(
    data: dict[str, Any], keys: list[str], value: Any, assignment: str, where: str
) -> None:
    node: Any = data
    for depth, key in enumerate(keys[:-1]):
        node = _child(node, key, assignment, where, keys[:depth])
    last = keys[-1]
    if isinstance(node, list) and last.isdigit() and int(last) < len(node):
        node[int(last)] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise ConfigError(f"{where}: --set {assignment!r}: {'.'.join(keys[:-1])} is not a table")


def _child(node: Any, key: str, assignment: str, where: str, parents: list[str]) -> Any:
    if isinstance(node, dict) and key in node:
        return node[key]
    if isinstance(node, list | tuple) and key.isdigit() and int(key) < len(node):
        return node[int(key)]
    at = ".".join(parents) or "the scenario"
    names = [str(k) for k in node] if isinstance(node, dict) else []
    hints = difflib.get_close_matches(key, names, n=1)
    hint = f" (did you mean {hints[0]!r}?)" if hints else ""
    raise ConfigError(f"{where}: --set {assignment!r}: {at} has no field {key!r}{hint}")


def toml_value(value: object) -> str:
    """`value` written as a TOML value, what `parse_value` (and so `--set` and
    `--driver-setting KEY=VALUE`) reads back; table keys bare where TOML allows it.
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return '"' + "".join(_escape(char) for char in value) + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    if isinstance(value, Mapping):
        pairs = (f"{_toml_key(str(k))} = {toml_value(v)}" for k, v in value.items())
        return "{ " + ", ".join(pairs) + " }"
    raise ConfigError(f"cannot write {value!r} as a TOML value")


def _escape(char: str) -> str:
    if char in '"\\':
        return "\\" + char
    if ord(char) < 0x20 or ord(char) == 0x7F:
        return f"\\u{ord(char):04x}"
    return char


def _toml_key(key: str) -> str:
    return key if _BARE_KEY.match(key) else toml_value(key)


def prior_map(scenario: Scenario) -> GridMap | None:
    """The prior map a scenario's fleet starts from (`navigation.prior_map`: a path, or a
    name under `configs/maps/`), None without one.
    """
    name = scenario.navigation.prior_map
    if not name:
        return None
    path = Path(name)
    if not path.exists() and not path.is_absolute():
        path = CONFIG_ROOT / "maps" / name
    return load_map(path)
