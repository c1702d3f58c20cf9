"""The checks behind a Run's validation (``run.validate_run``): the limits float32 poses set
on coordinates and headings, and the checks of single fields (types, the start pose, the
controls, the local maps' variances), each reporting through a ``fail(field, message)``
callback so that the caller's error names its file, field and frame."""

from __future__ import annotations

import math

import numpy as np

from gslam_jax import choices

__all__ = ["COORDINATE_FRACTION", "HEADING_LIMIT", "HEADING_STEP", "MAX_SPEED", "MAX_TURN",
           "check_controls", "check_start_pose", "check_statistics", "check_types", "coordinate_limit",
           "describe_cells", "float32_limit", "float32_spacing", "normalise_stored",
           "variance_tolerance"]


_REAL = "iuf"  # dtype kinds of real numbers (bool, complex, strings and objects are not)
_REAL_FIELDS = ("controls", "local_maps", "resolution", "timestamps", "ground_truth",
                "initial_pose", "lattice_headings")
# Local-map statistics may hold n sum z^2 - (sum z)^2 below 0 from rounding by up to
# max(VARIANCE_TOLERANCE, VARIANCE_ROUNDING * n * eps) relative to n |sum z^2| + (sum z)^2,
# eps that of the dtype the statistics were stored in (float32 sums of n heights round by up to
# about n eps relative each); more is a negative variance, i.e. corrupt statistics.
VARIANCE_TOLERANCE = 1e-6
VARIANCE_ROUNDING = 8.0


# The filter holds poses and the map origin in float32. A coordinate is resolved when float32's
# spacing there is at most COORDINATE_FRACTION of a map cell: poses then round by at most 1/512
# of a cell per frame, and a slow vehicle's millimetre steps at 0.1 m cells still register.
# At 0.16 m cells that holds within 8192 m of the origin; at 1e15 m the spacing is 125 km and
# every step of a path rounds away (the whole trajectory one position).
COORDINATE_FRACTION = 1.0 / 256.0
# Headings likewise: float32 spacing at most HEADING_STEP rad (1 mm at 10 m, a local map's edge),
# which holds below HEADING_LIMIT = 1024 rad (163 turns).
HEADING_STEP = 1e-4
# A control's heading change of more than pi in one frame cannot be told from the opposite turn
# (the heading is only known modulo 2 pi between frames; VO reports its rotation in (-pi, pi]), so
# no frame of real data holds one: it is a corrupt, mis-scaled (degrees) or unwrapped value.
MAX_TURN = float(np.pi)
# A control faster than this between its frame's timestamps (three times the land speed record
# of 341 m/s) is no vehicle's motion but a mis-scaled or corrupt step; metres per second.
MAX_SPEED = 1000.0


def float32_limit(step: float) -> float:
    """The largest magnitude below which float32 numbers are spaced at most ``step`` apart: a
    power of two, 2^(k + 24) with 2^k the largest power of two <= ``step`` (float32 numbers in
    [2^e, 2^(e+1)) are 2^(e-23) apart)."""
    return math.ldexp(1.0, math.floor(math.log2(step)) + 24)


def float32_spacing(x: float) -> float:
    """The distance between float32 numbers at magnitude ``x`` (inf beyond float32's range)."""
    x = abs(float(x))
    if x >= float(np.finfo(np.float32).max):
        return math.inf
    tiny = float(np.finfo(np.float32).smallest_subnormal)
    return max(math.ldexp(1.0, math.frexp(x)[1] - 24), tiny) if x else tiny


def coordinate_limit(resolution: float) -> float:
    """Metres from the origin within which float32 resolves COORDINATE_FRACTION of a map cell
    of ``resolution`` metres (the limit on the start pose and the map extent)."""
    return float32_limit(COORDINATE_FRACTION * resolution)


HEADING_LIMIT = float32_limit(HEADING_STEP)


def check_start_pose(pose: np.ndarray, resolution: float, fail) -> None:
    """``fail("initial_pose", msg)`` when a start pose's position lies beyond
    ``coordinate_limit(resolution)`` or its heading beyond HEADING_LIMIT: float32, in which the
    filter holds poses, would not resolve the map's cells (or the heading) there."""
    limit = coordinate_limit(resolution)
    far = float(np.max(np.abs(pose[:2])))
    if far >= limit:
        fail("initial_pose", f"position ({pose[0]:.6g}, {pose[1]:.6g}) m is {far:.4g} m from "
             f"the origin; the filter's float32 poses there are "
             f"{float32_spacing(far):.3g} m apart, coarser than 1/"
             f"{1 / COORDINATE_FRACTION:.0f} of the {resolution:g} m cells (at most {limit:g} m "
             "from the origin at this resolution); give the start pose in a local frame (e.g. "
             "subtract the first position from every position)")
    if abs(float(pose[2])) >= HEADING_LIMIT:
        fail("initial_pose", f"heading {float(pose[2]):.6g} rad is beyond {HEADING_LIMIT:g} rad, "
             f"where float32 headings are more than {HEADING_STEP:g} rad apart; give it modulo "
             "2 pi")


def check_controls(controls: np.ndarray, timestamps: np.ndarray, fail) -> None:
    """``fail("controls", msg)`` naming the first frame whose control turns by more than
    MAX_TURN or moves faster than MAX_SPEED between its timestamps (frame 0, which moves from the
    initial pose, against the median frame interval): neither is a vehicle's motion."""
    turn = np.abs(controls[:, 2])
    if (turn > MAX_TURN).any():
        t = int(np.argmax(turn > MAX_TURN))
        fail("controls", f"frame {t} turns {controls[t, 2]:.6g} rad in one frame (more than pi: "
             f"no heading change a frame can express; {int(np.sum(turn > MAX_TURN))} frames in "
             "all); store the heading increment in radians within [-pi, pi]")
    if controls.shape[0] < 2:
        return
    dt = np.diff(timestamps)
    dt = np.concatenate([[np.median(dt)], dt])
    step = np.hypot(controls[:, 0], controls[:, 1])
    fast = step > MAX_SPEED * dt
    if fast.any():
        t = int(np.argmax(fast))
        fail("controls", f"frame {t} moves {step[t]:.6g} m in {dt[t]:.4g} s ({step[t] / dt[t]:.4g} "
             f"m/s, more than {MAX_SPEED:g} m/s; {int(np.sum(fast))} frames in all): a "
             "mis-scaled or corrupt control (controls are metres, timestamps seconds)")


BLOCK_MAPS = 32  # local maps checked at a time: the checks' temporaries stay a block's size


def _blocks(maps: np.ndarray):
    """``maps`` [M, ...] in consecutive blocks of ``BLOCK_MAPS`` along the first axis."""
    for start in range(0, maps.shape[0], BLOCK_MAPS):
        yield maps[start:start + BLOCK_MAPS]


def _rounding_dtype(maps: np.ndarray, stored: np.dtype) -> np.dtype:
    """The dtype whose eps bounds the statistics' rounding (``variance_tolerance``)."""
    stored = np.dtype(stored)
    if stored.kind != "f":
        return np.dtype(np.float64)
    if stored.itemsize > 4:
        with np.errstate(over="ignore", invalid="ignore"):
            if all(np.array_equal(b.astype(np.float32), b) for b in _blocks(maps)):
                return np.dtype(np.float32)
    return stored


def _tolerance(n: np.ndarray, eps: float) -> np.ndarray:
    """max(VARIANCE_TOLERANCE, VARIANCE_ROUNDING n eps) for point counts ``n`` (float64)."""
    return np.maximum(VARIANCE_TOLERANCE, VARIANCE_ROUNDING * n * eps)


def variance_tolerance(maps: np.ndarray, stored: np.dtype) -> np.ndarray:
    """[M, L, L] relative tolerance of n sum z^2 - (sum z)^2 < 0 for the statistics ``maps``
    [M, L, L, 3] stored as ``stored``: max(VARIANCE_TOLERANCE, VARIANCE_ROUNDING n eps).

    eps is the stored dtype's; integers (no rounding of their own) count as float64, and wider
    floats whose every value is a float32 count as float32 (statistics accumulated in float32
    and widened, e.g. a float32 Run file loaded and saved again)."""
    eps = np.finfo(_rounding_dtype(maps, stored)).eps
    return _tolerance(np.asarray(maps[..., 0], np.float64), eps)


def check_statistics(maps: np.ndarray, stored: np.dtype, fail, where) -> None:
    """Local-map statistics [M, L, L, 3] (n, sum z, sum z^2) as only point heights give them:
    finite, n a whole number >= 0, the variance not negative beyond ``variance_tolerance``.
    ``fail(message)`` raises; ``where(bad_cells [M, L, L])`` names the first bad cell.
    The maps are checked ``BLOCK_MAPS`` at a time, so the check needs a block's temporaries,
    not several copies of all the maps; the whole mask is built only for a failing check."""
    eps = np.finfo(_rounding_dtype(maps, stored)).eps

    def non_finite(b: np.ndarray) -> np.ndarray:
        return ~np.isfinite(b).all(axis=-1)

    def negative_n(b: np.ndarray) -> np.ndarray:
        return b[..., 0].astype(np.float64) < 0

    def fractional_n(b: np.ndarray) -> np.ndarray:
        n = b[..., 0].astype(np.float64)
        return n != np.round(n)

    def negative_variance(b: np.ndarray) -> np.ndarray:
        n, sz, szz = (b[..., c].astype(np.float64) for c in range(3))
        spread = n * szz - sz * sz  # n^2 times the variance of the heights
        return spread < -_tolerance(n, eps) * (n * np.abs(szz) + sz * sz)

    for bad, message in ((non_finite, "non-finite statistics in {}"),
                         (negative_n, "negative point count n in {}"),
                         (fractional_n, "non-integer point count n in {}"),
                         (negative_variance,
                          "negative variance (n sum z^2 < (sum z)^2) in {}")):
        with np.errstate(invalid="ignore", over="ignore"):
            if any(bad(b).any() for b in _blocks(maps)):
                fail(message.format(where(np.concatenate([bad(b) for b in _blocks(maps)]))))


def describe_cells(bad_cells: np.ndarray, obs_index: np.ndarray) -> str:
    """'local map m (frame t), cell (i, j) (c cells in all)' of the first true cell of
    ``bad_cells`` [M, L, L]; frame t is the first frame that uses local map m."""
    m, i, j = (int(v) for v in np.argwhere(bad_cells)[0])
    frames = np.flatnonzero(np.asarray(obs_index) == m)
    at = f"frame {int(frames[0])}" if frames.size else "used by no frame"
    return f"local map {m} ({at}), cell ({i}, {j}) ({int(np.sum(bad_cells))} cells in all)"


def normalise_stored(fields: dict, fail) -> dict:
    """Older Run files' encodings, converted: ``vo_failed`` as integers 0/1 (to bool) and
    ``resolution`` as a size-1 array (to a scalar). Other integers in ``vo_failed`` fail naming
    the first bad frame; everything else is left to ``_check_types``."""
    fields = dict(fields)
    flags = fields.get("vo_failed")
    if flags is not None and flags.dtype.kind in "iu" and flags.ndim == 1:
        bad = (flags != 0) & (flags != 1)
        if bad.any():
            t = int(np.argmax(bad))
            fail("vo_failed", f"expected bool or integers 0/1, got {flags[t]} at frame {t} "
                 f"({int(bad.sum())} frames in all)")
        fields["vo_failed"] = flags.astype(bool)
    res = fields["resolution"]
    if res.shape != () and res.size == 1:
        fields["resolution"] = res.reshape(())
    return fields


def check_types(fields: dict, fail) -> None:
    """Field types before any conversion: real numbers, integer indices, bool flags, a scalar
    resolution (``fail(field, msg)`` raises)."""
    for name in _REAL_FIELDS:
        value = fields.get(name)
        if value is not None and np.asarray(value).dtype.kind not in _REAL:
            fail(name, f"expected real numbers, got dtype {np.asarray(value).dtype}")
    if np.asarray(fields["resolution"]).shape != ():
        fail("resolution", f"expected a scalar, got shape {np.asarray(fields['resolution']).shape}")
    if fields.get("vo_failed") is not None and np.asarray(fields["vo_failed"]).dtype != bool:
        fail("vo_failed", f"expected bool, got dtype {np.asarray(fields['vo_failed']).dtype}")
    kind = np.asarray(fields["controls"]).dtype
    if kind.kind in "iu":  # whole metres and radians only: surely truncated on the way
        fail("controls", f"stored as integers ({kind}), so only whole metres and radians; "
             "store the increments as floating point")
    sensor = fields.get("sensor")
    if sensor is not None and (np.asarray(sensor).shape != () or
                               str(np.asarray(sensor)) not in choices.SENSORS):
        fail("sensor", f"expected one of {', '.join(choices.SENSORS)}, "
             f"got {np.asarray(sensor)!s:.40}")
    origin = fields.get("time_origin_ns")
    if origin is not None and (np.asarray(origin).shape != () or
                               np.asarray(origin).dtype.kind not in "iu"):
        fail("time_origin_ns", f"expected one integer (nanoseconds), got "
             f"{np.asarray(origin).dtype} of shape {np.asarray(origin).shape}")
