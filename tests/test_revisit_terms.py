"""experiments/revisit_terms.py: lineages through resamplings, the old / new split of a
particle's known cells, and a small loop run end to end."""

from __future__ import annotations

import math

import numpy as np

from experiments import revisit_terms as rt


def test_carry_lineage_traces_each_slot_back_to_its_snapshot_ancestor():
    rng = np.random.default_rng(0)
    J, n = 7, 5
    ancestors = rng.integers(0, J, (n, J))
    start = rng.permutation(J)  # the lineage carried in from earlier chunks
    got = rt.carry_lineage(start, ancestors)
    for j in range(J):
        slot = j
        for t in reversed(range(n)):  # the parent of slot at frame t, back to the snapshot
            slot = ancestors[t, slot]
        assert got[j] == start[slot]
    # in two chunks as in one
    np.testing.assert_array_equal(rt.carry_lineage(rt.carry_lineage(start, ancestors[:2]),
                                                   ancestors[2:]), got)


def test_split_terms_on_hand_made_cells():
    known = np.array([[1, 1, 1, 1, 0], [1, 1, 0, 0, 0], [0, 0, 0, 0, 1]], bool)
    before = np.array([[1, 0, 1, 0, 1], [1, 1, 1, 1, 1], [0, 0, 0, 0, 0]], bool)
    lam = np.array([[4.0, 2.0, 6.0, 0.0, 9.0], [1.0, 3.0, 7.0, 7.0, 7.0],
                    [0.0, 0.0, 0.0, 0.0, 5.0]])
    s = rt.split_terms(known, before, lam)
    np.testing.assert_allclose(s["old_share"], [0.5, 1.0, 0.0])
    np.testing.assert_allclose(s["per_cell_old"], [5.0, 2.0, np.nan])
    np.testing.assert_allclose(s["per_cell_new"], [1.0, np.nan, 5.0])
    np.testing.assert_allclose(s["per_cell"], [3.0, 2.0, 5.0])
    m = rt.group_medians(s, {"near": np.array([True, True, False]),
                             "far": np.array([False, False, False])})
    assert m["old_share_near"] == 0.75 and m["per_cell_new_near"] == 1.0
    assert math.isnan(m["old_share_far"])


def test_revisit_terms_runs_a_small_circle(tmp_path):
    out = tmp_path / "rows.json"
    rows = rt.main(["--circle", "40", "--course", "mars-yard-a", "--seed", "0",
                    "--set", "filter.particles=8", "--set", "filter.unknown_cells=sample",
                    "--after", "6", "--chunk", "8", "--json", str(out)])
    assert rows and out.exists()
    travel = [r["travel_m"] for r in rows]
    assert travel == sorted(travel) and travel[-1] > 20
    for r in rows:
        assert r["near"] + r["far"] <= 8
        for g in ("near", "far"):
            share = r[f"old_share_{g}"]
            assert math.isnan(share) or 0.0 <= share <= 1.0
    # the first row follows the snapshot by one chunk: most of its known cells are old
    first = rows[0]
    shares = [first[f"old_share_{g}"] for g in ("near", "far")]
    assert max(s for s in shares if not math.isnan(s)) > 0.5
