"""The log-gamma weights and their per-particle reduction, read from the compiled HLO.

DESIGN.md asks that the log-gamma terms of all (particle, cell) pairs and their reduction to one
log lambda per particle be one fused XLA computation, verified rather than assumed. What XLA
(jax 0.10.2, CPU) actually produces for ``jax.vmap(importance.log_importance)`` over [J, W, W]
windows, and what these tests pin down:

* One elementwise loop fusion per importance term holds every lgamma table lookup (``gather``
  from the f32[LGAMMA_TABLE_SIZE] table and from the small-k difference table) together with
  the log / log1p ops of that term (the Stirling difference, and log m, log1p(-m) of the
  smaller variance ratio). No lookup sits in a fusion without logs, and no table is read
  anywhere else.
  In "ignore" mode that is a single fusion holding *all* logs of the computation. In "sample"
  mode there are two such fusions (G_prev and G_new terms of eq. 31); log S and log k of the
  observation are shared by both terms, so XLA computes each once in a small producer fusion
  (one log each) that feeds both term fusions.
* The per-particle sum is not inside that loop fusion: XLA outlines it as a separate
  ``kind=kCustom`` fusion with backend config ``__ynn_fusion`` (a YNNPACK reduction) that
  contains the ``reduce`` and takes the elementwise fusion's output directly as its operand,
  f32[J, W, W] -> f32[J]. So the result is "one loop fusion plus the reduction that directly
  consumes it" rather than one fusion; the [J, W, W] terms are materialised once between them.
  The test accepts either form (reduce inside the same fusion, or a fusion whose only job is
  the reduce reading the term fusion directly) so that it keeps passing if XLA fuses them.
* The cell-count reductions (N_prev, N_obs) are integer reductions of masks only and are not
  part of the log-gamma computation.

Checked for ``cells.log_predictive_integer`` behind ``importance.log_importance``. ``rbpf.update``
runs the same kernel with log v of the observation passed in (computed once per update for all
particles), which only moves those two logs out of the per-particle fusion.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import pytest

from gslam_jax.rbpf import cells
from gslam_jax import rbpf
from gslam_jax.rbpf.importance import _log_importance, log_importance

J, WN = 16, 96

_COMP = re.compile(r"^(?:ENTRY )?%([\w.\-]+) \(")
_INSTR = re.compile(r"^\s*(?:ROOT )?%([\w.\-]+) = (.+?) ([\w\-]+)\((.*)$")


@dataclass
class Fusion:
    name: str
    kind: str
    shape: str
    operands: list[str]
    ops: list[str]          # opcodes inside the fused computation
    inner_params: dict      # parameter index -> shape inside the fused computation
    ynn: bool


def _parse(hlo: str) -> list[Fusion]:
    comps: dict[str, list[str]] = {}
    cur = None
    for line in hlo.splitlines():
        m = _COMP.match(line)
        if m:
            cur = m.group(1)
            comps[cur] = []
        elif cur is not None and line.strip() and line.strip() != "}":
            comps[cur].append(line)
    fusions = []
    for body in comps.values():
        for line in body:
            m = _INSTR.match(line)
            if not m or m.group(3) != "fusion":
                continue
            name, shape, _, rest = m.groups()
            kind = re.search(r"kind=(\w+)", rest).group(1)
            called = re.search(r"calls=%([\w.\-]+)", rest).group(1)
            operands = re.findall(r"%([\w.\-]+)", rest.split("), kind=")[0])
            ops, params = [], {}
            for inner in comps[called]:
                im = _INSTR.match(inner)
                if not im:
                    continue
                ops.append(im.group(3))
                if im.group(3) == "parameter":
                    idx = int(re.match(r"(\d+)\)", im.group(4)).group(1))
                    params[idx] = im.group(2)
            fusions.append(Fusion(name, kind, shape, operands, ops, params,
                                  "__ynn_fusion" in line))
    return fusions


def _logs(f: Fusion) -> int:
    return sum(op in ("log", "log-plus-one") for op in f.ops)


def _compiled(mode: str, log_pred) -> list[Fusion]:
    params = rbpf.FilterParams()
    x = jnp.ones((J, WN, WN), jnp.float32)
    fn = jax.jit(jax.vmap(lambda *a: _log_importance(*a, params, mode, log_pred)))
    if log_pred is cells.log_predictive_integer:  # the public entry point, same computation
        fn = jax.jit(jax.vmap(lambda *a: log_importance(*a, params, mode)))
    hlo = fn.lower(x, x, x, x, x, x, jnp.ones((J,), bool)).compile().as_text()
    return _parse(hlo)


def _is_table(shape: str) -> bool:
    return shape.startswith(f"f32[{cells.LGAMMA_TABLE_SIZE}]") or shape.startswith("f32[256]")


@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_log_gamma_terms_are_fused_and_reduced_directly(mode):
    fusions = _compiled(mode, cells.log_predictive_integer)
    by_name = {f.name: f for f in fusions}
    terms = 1 if mode == "ignore" else 2

    # The fusions holding lgamma table lookups: one per importance term, each with its logs.
    lookup = [f for f in fusions if "gather" in f.ops]
    assert len(lookup) == terms, [f.name for f in lookup]
    for f in lookup:
        assert f.kind == "kLoop"
        assert any(_is_table(s) for s in f.inner_params.values()), f.inner_params
        assert _logs(f) >= 4, (f.name, f.ops)  # Stirling difference + log m + log1p(-m) at least
        assert f.shape.startswith(f"f32[{J},{WN},{WN}]"), f.shape
    # Every log op of the computation is in those fusions, except (sample mode) log S and log k
    # of the observation, each computed once in a one-log producer feeding both term fusions.
    others = [f for f in fusions if f not in lookup and _logs(f)]
    if mode == "ignore":
        assert others == []
    else:
        assert len(others) == 2, [f.name for f in others]
        for f in others:
            assert _logs(f) == 1 and "gather" not in f.ops
            assert all(f.name in t.operands for t in lookup), (f.name, [t.operands for t in lookup])

    # The per-particle reduction: in the same fusion, or a fusion doing only the reduce that
    # reads the term fusion's output directly (XLA 0.10.2 CPU: a kCustom __ynn_fusion).
    for f in lookup:
        if "reduce" in f.ops:
            continue
        consumers = [g for g in fusions if f.name in g.operands]
        reducers = [g for g in consumers if "reduce" in g.ops]
        assert len(reducers) == 1 and consumers == reducers, [g.name for g in consumers]
        red = reducers[0]
        assert red.shape.startswith(f"f32[{J}]"), red.shape
        assert _logs(red) == 0 and "gather" not in red.ops
        assert set(red.ops) <= {"parameter", "constant", "reduce", "add", "bitcast", "reshape"}
        # what XLA produced on this version: a YNNPACK custom fusion
        if red.kind == "kCustom":
            assert red.ynn
        assert by_name[red.name] is red


def test_sample_mode_with_padded_draw_rows_keeps_the_slice_out_of_the_terms():
    """Eq. 31 with the D draws as the update passes them and M cells not a multiple of D: the
    cells are padded to [ceil(M / D), D] rows, and the new-cell term is summed on those rows.
    A slice back to M before the sum put ``slice`` into the lookup fusion, which XLA CPU then
    ran 2-3x slower (``gslam bench --local 66 --mode sample``)."""
    M, D = 200, 64
    params = rbpf.FilterParams()
    cells_ = jnp.ones((J, M), jnp.float32)
    draws = jnp.ones((J, D), jnp.float32)
    fn = jax.jit(jax.vmap(lambda k, S, kp, Sp, kd, Sd, b: _log_importance(
        k, S, kp, Sp, kd, Sd, b, params, "sample")))
    fusions = _parse(fn.lower(cells_, cells_, cells_, cells_, draws, draws,
                              jnp.ones((J,), bool)).compile().as_text())
    lookup = [f for f in fusions if "gather" in f.ops]
    assert len(lookup) == 2, [f.name for f in lookup]
    for f in lookup:
        assert "slice" not in f.ops, (f.name, f.ops)
