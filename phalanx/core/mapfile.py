"""Occupancy maps in the format robot users already have: ROS's map_server (an image,
PGM or PNG, and a YAML header: `image`, `resolution`, `origin`, `negate`,
`occupied_thresh`, `free_thresh`, `mode`), read and written.

How map_server reads a pixel (its documentation, "map_server", ROS wiki): the pixel's
value (the mean of its channels) becomes an occupancy probability
`p = (255 - value) / 255` (`value / 255` with `negate: 1`); above `occupied_thresh` it
is occupied, below `free_thresh` free, unknown between (`mode: trinary` and `scale`).
`mode: raw` takes the value itself as a percentage (0-100, anything else unknown). The
image's lower-left pixel is at `origin` (x, y in m, yaw in rad) of the map frame, which
here is the scenario's world frame. Written maps are trinary PGMs: 0 occupied, 254
free, 205 unknown, as map_saver writes them.

Everything in the user's files is checked: the YAML's size, keys and value ranges, the
image's path (next to the YAML unless absolute), format and size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from phalanx.core.errors import ConfigError

UNKNOWN, FREE, OCCUPIED = -1, 0, 100
MAX_YAML_BYTES = 64 * 1024
MAX_PIXELS = 8192 * 8192
MAX_ORIGIN_M = 1e5
_FREE_PIXEL, _OCCUPIED_PIXEL, _UNKNOWN_PIXEL = 254, 0, 205


class MapHeader(BaseModel):
    """The YAML header of a map_server map (SI units: m, rad)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    image: Annotated[str, Field(min_length=1, max_length=4096)]
    resolution: Annotated[float, Field(ge=0.005, le=5.0)]
    origin: tuple[float, float, float]
    negate: Literal[0, 1] = 0
    occupied_thresh: Annotated[float, Field(ge=0.0, le=1.0)] = 0.65
    free_thresh: Annotated[float, Field(ge=0.0, le=1.0)] = 0.196
    mode: Literal["trinary", "scale", "raw"] = "trinary"

    @field_validator("origin")
    @classmethod
    def _origin_on_earth(cls, origin: tuple[float, float, float]) -> tuple[float, float, float]:
        x, y, yaw = origin
        if not all(math.isfinite(v) for v in origin):
            raise ValueError(f"origin must be finite numbers, got {list(origin)}")
        if abs(x) > MAX_ORIGIN_M or abs(y) > MAX_ORIGIN_M or abs(yaw) > 2 * math.pi:
            raise ValueError(
                f"origin must be within {MAX_ORIGIN_M:g} m and 2 pi rad, got {list(origin)}"
            )
        return origin

    def model_post_init(self, context: object, /) -> None:
        """The free threshold lies below the occupied one."""
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError(
                f"free_thresh ({self.free_thresh}) must be below occupied_thresh "
                f"({self.occupied_thresh})"
            )


@dataclass(frozen=True)
class GridMap:
    """An occupancy grid: `cells[row, col]` is UNKNOWN (-1), FREE (0) or OCCUPIED (100),
    row 0 at the bottom (y = origin's y), `resolution_m` per cell, the lower-left
    corner of cell (0, 0) at `origin` (x_m, y_m, yaw_rad) of the world frame.
    """

    cells: npt.NDArray[np.int8]
    resolution_m: float
    origin: tuple[float, float, float]

    def centres(self, which: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """World x, y (m) of the centres of the cells holding `which`."""
        rows, cols = np.nonzero(self.cells == which)
        px = (cols + 0.5) * self.resolution_m
        py = (rows + 0.5) * self.resolution_m
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        return x0 + c * px - s * py, y0 + s * px + c * py


def _read_header(path: Path) -> MapHeader:
    import yaml  # type: ignore[import-untyped, unused-ignore]

    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the map file ({exc.strerror})") from exc
    if size > MAX_YAML_BYTES:
        raise ConfigError(f"{path}: a map header is at most {MAX_YAML_BYTES} bytes, got {size}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a YAML map header ({exc})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a YAML mapping (image, resolution, origin, ...)")
    try:
        return MapHeader.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'header'}: {e['msg']}" for e in exc.errors()
        )
        raise ConfigError(f"{path}: {problems}") from exc


def _pixels(path: Path) -> npt.NDArray[np.float64]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            width, height = image.size
            if width * height > MAX_PIXELS or width < 1 or height < 1:
                raise ConfigError(
                    f"{path}: a map image has 1 to {MAX_PIXELS} pixels, got {width} x {height}"
                )
            bands = image.convert("RGB") if image.mode not in ("L", "I", "I;16", "1") else image
            array = np.asarray(bands, dtype=np.float64)
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as exc:
        raise ConfigError(f"{path}: cannot read the map image ({exc})") from exc
    if array.ndim == 3:
        array = array.mean(axis=2)  # map_server averages the colour channels
    return np.clip(array, 0.0, 255.0)


def load_map(path: str | Path) -> GridMap:
    """Read a map_server map (the YAML header's path): its cells, resolution, origin."""
    yaml_path = Path(path)
    header = _read_header(yaml_path)
    image = Path(header.image)
    if not image.is_absolute():
        image = yaml_path.parent / image
    values = _pixels(image)[::-1]  # the image's top row is the map's last
    cells = np.full(values.shape, UNKNOWN, dtype=np.int8)
    if header.mode == "raw":
        known = values <= 100.0
        cells[known & (values > 100.0 * header.occupied_thresh)] = OCCUPIED
        cells[known & (values < 100.0 * header.free_thresh)] = FREE
    else:
        p = values / 255.0 if header.negate else (255.0 - values) / 255.0
        cells[p > header.occupied_thresh] = OCCUPIED
        cells[p < header.free_thresh] = FREE
    return GridMap(cells, header.resolution, header.origin)


def save_map(grid: GridMap, yaml_path: str | Path) -> Path:
    """Write `grid` as a trinary PGM and its YAML header (`<name>.pgm` beside it)."""
    yaml_path = Path(yaml_path)
    image_path = yaml_path.with_suffix(".pgm")
    pixels = np.full(grid.cells.shape, _UNKNOWN_PIXEL, dtype=np.uint8)
    pixels[grid.cells == FREE] = _FREE_PIXEL
    pixels[grid.cells == OCCUPIED] = _OCCUPIED_PIXEL
    height, width = grid.cells.shape[:2]
    header = f"P5\n# phalanx fleet map\n{width} {height}\n255\n".encode("ascii")
    image_path.write_bytes(header + pixels[::-1].tobytes())
    x0, y0, yaw = grid.origin
    yaml_path.write_text(
        f"image: {image_path.name}\n"
        f"resolution: {grid.resolution_m!r}\n"
        f"origin: [{x0!r}, {y0!r}, {yaw!r}]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\nmode: trinary\n",
        encoding="utf-8",
    )
    return image_path
