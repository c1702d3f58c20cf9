"""GPS log files: (time, latitude, longitude, EPE) text/CSV readings, read into a UTM site frame.

The reader returns positions as UTM minus a float64 ``origin`` (the paper's site frame, Fig. 12),
so the JAX alignment works on metres that float32 holds exactly enough; host code adds the origin
back in float64.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
from jax.typing import ArrayLike

from gslam_jax.errors import InputError
from gslam_jax.gps.utm import UTM_LATITUDES, latlon_to_utm, utm_epsg

__all__ = ["GpsLog", "GpsLogError", "read_gps_log", "write_gps_log"]

class GpsLogError(InputError):
    """A GPS log is malformed; the message names the file and line."""


class GpsLog(NamedTuple):
    """GPS readings in a UTM site frame (float64 NumPy).

    time [N] s; lat, lon [N] degrees; epe [N] m; xy [N,2] = UTM (E, N) - origin; origin (2,)
    the site-frame origin in UTM metres; zone, north the UTM zone; n_skipped the readings
    dropped while reading (NaN coordinates, EPE <= 0 or not finite); lines [N] the 1-based
    line of each reading in its file (None for simulated readings).
    """

    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    epe: np.ndarray
    xy: np.ndarray
    origin: np.ndarray
    zone: int
    north: bool
    n_skipped: int = 0
    lines: np.ndarray | None = None

    @property
    def epsg(self) -> int:
        return utm_epsg(self.zone, self.north)


_ALIASES = {
    "time": ("time", "t", "timestamp", "stamp", "sec", "secs", "seconds", "time_s"),
    "lat": ("lat", "latitude", "lat_deg"),
    "lon": ("lon", "lng", "long", "longitude", "lon_deg"),
    "epe": ("epe", "hepe", "epe_m", "sigma", "accuracy", "horizontal_accuracy", "eph"),
}


def _split(line: str) -> list[str]:
    line = line.strip()
    return [s.strip() for s in re.split(r"[,;\t]" if re.search(r"[,;\t]", line) else r"\s+",
                                        line)]


def read_gps_log(path: str | Path, origin: ArrayLike | None = None, zone: int | None = None,
                 strict: bool = False) -> GpsLog:
    """Read a text/CSV GPS log of (time, latitude, longitude, EPE) and convert to UTM.

    Separators: comma, semicolon, tab or whitespace; '#' starts a comment. An optional header
    line names the columns (e.g. ``time,lat,lon,epe``; common aliases accepted, extra columns
    ignored); without one the first four columns are taken in that order. Readings with a NaN
    coordinate or a non-positive/non-finite EPE are skipped and counted (``strict=True``
    raises instead). The UTM zone comes from the first reading unless given; ``origin`` (UTM
    E, N) defaults to the first reading rounded to 100 m. Raises GpsLogError naming the file
    and line for unparsable lines, decreasing time, a latitude or longitude out of range (or
    outside UTM's latitudes), or < 2 usable readings (with the first skipped reading's reason).
    """
    path = Path(path)
    cols = {"time": 0, "lat": 1, "lon": 2, "epe": 3}
    rows: list[tuple[float, float, float, float]] = []
    lines: list[int] = []
    skipped, seen_data, first_skip = 0, False, ""
    try:
        text = path.read_text()
    except OSError as err:
        raise GpsLogError(f"{path}: cannot read GPS log ({err})") from err
    last_t, last_line = -np.inf, 0
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = _split(line)
        if not seen_data and not _is_number(fields[0]):
            names = [f.lower() for f in fields]
            cols = {}
            for key, aliases in _ALIASES.items():
                hit = [i for i, nm in enumerate(names) if nm in aliases]
                if not hit:
                    raise GpsLogError(f"{path}:{lineno}: header has no '{key}' column "
                                      f"(accepted names: {', '.join(aliases)}); got {fields}")
                cols[key] = hit[0]
            seen_data = True  # only one header line
            continue
        seen_data = True
        need = max(cols.values()) + 1
        if len(fields) < need:
            raise GpsLogError(f"{path}:{lineno}: expected at least {need} fields "
                              f"(time, lat, lon, epe), got {len(fields)}: {raw.strip()!r}")
        try:
            t, la, lo, ep = (float(fields[cols[k]]) for k in ("time", "lat", "lon", "epe"))
        except ValueError:
            raise GpsLogError(f"{path}:{lineno}: not a number in {raw.strip()!r}") from None
        if not math.isfinite(t):
            raise GpsLogError(f"{path}:{lineno}: time is not finite ({fields[cols['time']]})")
        if t < last_t:
            raise GpsLogError(f"{path}:{lineno}: time {t} goes backwards "
                              f"(line {last_line} had {last_t})")
        last_t, last_line = t, lineno
        bad = None
        if not (math.isfinite(la) and math.isfinite(lo)):
            bad = "non-finite coordinate"
        elif not (-90.0 <= la <= 90.0 and -180.0 <= lo <= 360.0):
            swapped = -90.0 <= lo <= 90.0 and -180.0 <= la <= 360.0
            what = (f"latitude {la} is out of range (-90 to 90)" if not -90.0 <= la <= 90.0
                    else f"longitude {lo} is out of range (-180 to 360)")
            raise GpsLogError(f"{path}:{lineno}: {what}"
                              + ("; are latitude and longitude swapped? (the columns are "
                                 f"{_column_order(cols)})" if swapped else ""))
        elif not (math.isfinite(ep) and ep > 0):
            bad = f"EPE must be positive and finite, got {ep}"
        if bad is None and not UTM_LATITUDES[0] <= la <= UTM_LATITUDES[1]:
            raise GpsLogError(f"{path}:{lineno}: latitude {la} is outside UTM's range "
                              f"({-UTM_LATITUDES[0]:g} S to {UTM_LATITUDES[1]:g} N); polar "
                              "sites need UPS, which gslam does not implement")
        if bad is not None:
            if strict:
                raise GpsLogError(f"{path}:{lineno}: {bad}")
            skipped += 1
            first_skip = first_skip or f"; the first skipped, line {lineno}: {bad}"
            continue
        rows.append((t, la, lo, ep))
        lines.append(lineno)
    if len(rows) < 2:
        raise GpsLogError(f"{path}: need at least 2 usable GPS readings, found {len(rows)} "
                          f"({skipped} skipped){first_skip}")
    arr = np.asarray(rows, np.float64)
    E, N, zone, north = latlon_to_utm(arr[:, 1], arr[:, 2], zone=zone)
    if origin is None:
        origin = np.round(np.array([E[0], N[0]]) / 100.0) * 100.0
    origin = np.asarray(origin, np.float64)
    xy = np.stack([E, N], -1) - origin
    return GpsLog(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], xy, origin, zone, north, skipped,
                  np.asarray(lines, np.int64))


def _column_order(cols: dict[str, int]) -> str:
    """The columns read, in file order (e.g. 'time, lat, lon, epe')."""
    return ", ".join(sorted(cols, key=cols.get))


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def write_gps_log(path: str | Path, time: ArrayLike, lat: ArrayLike, lon: ArrayLike,
                  epe: ArrayLike) -> None:
    """Write a CSV GPS log with header ``time,lat,lon,epe`` (readable by ``read_gps_log``)."""
    arr = np.stack([np.asarray(v, np.float64) for v in (time, lat, lon, epe)], -1)
    np.savetxt(path, arr, delimiter=",", header="time,lat,lon,epe", comments="",
               fmt=["%.3f", "%.9f", "%.9f", "%.3f"])
