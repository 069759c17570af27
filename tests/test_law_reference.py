"""The control step against what it computed when tests/data/law_reference.npz was written.

Every stored case (tests/law_reference.py) is replayed open loop through the current
:func:`pneutune.control.law.darc.step_into`, from its stored initial state and packed config,
on its stored measurement sequence; the duties, the Eq. (33) case of every step and the stored
state vectors must agree.

Tolerance: 1e-9 relative, with an absolute floor. The check on an element is
``|new - stored| <= 1e-9 * max(|stored|, floor)``. Many of the quantities pass through zero
(e1, e2, e3, dF_pd, τ, dθ̂/dt, Q_Ld, the dither accumulators), where a relative error means
nothing: an equivalent implementation that orders its floating-point operations differently
moves them by rounding of the size of the terms they are made of, not of their value. So the
floor is the full scale of the quantity: 1 for a duty, and for a state slot its largest
magnitude over the case's stored states. A slot that is exactly 0 throughout (the PID integral
of a DARC variant) has floor 0 and must stay exactly 0. The cases must be equal: they are
integers. The Kalman scratch (state slots from ``S_WORK`` on) has no meaning between steps and
is not compared. With the implementation the file was written by, every difference is 0.

A second test checks that the file covers every variant, both PWM update modes, both dead-zone
modes, both position feedbacks and every Eq. (33) case, so that a shrunken file fails.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from law_reference import (
    DURATION,
    FORMAT,
    LAW_VARIANTS,
    REFERENCE,
    compare_case,
    load_reference,
    reference_cases,
    state_rows,
)

from pneutune.control.constants import PWM_UPDATE_MODES
from pneutune.control.contracts.controller import (
    DEAD_ZONE_MODES,
    ORIGINAL_DARC_ACCEL,
    POSITION_FEEDBACK,
    VARIANTS,
)
from pneutune.control.law.darc import MEAS_SIZE, S_WORK, STATE_SIZE
from pneutune.control.law.layout import (
    CFG_DZ_MODE,
    CFG_LAYOUT_ID,
    CFG_ORIG_ACCEL,
    CFG_POS_FB,
    CFG_SIZE,
    CFG_TS,
    CFG_VARIANT,
)
from pneutune.control.sim.scenarios import GROUPS

RTOL = 1e-9


@pytest.fixture(scope="module")
def reference() -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The file's JSON index and arrays."""
    return load_reference(REFERENCE)


def test_replay_matches_reference(reference: tuple[dict[str, Any], dict[str, np.ndarray]]) -> None:
    """Every stored case replays to the stored duties, cases and states (module docstring)."""
    index, arrays = reference
    assert index["format"] == FORMAT
    assert (index["meas_size"], index["state_size"], index["cfg_size"],
            index["cfg_layout_id"]) == (MEAS_SIZE, STATE_SIZE, CFG_SIZE, CFG_LAYOUT_ID), (
        "the measurement, state or config layout changed since the file was written: the "
        "stored vectors no longer mean the same thing (rewrite the file only for a deliberate "
        "change of the law: python tests/law_reference.py --write)")
    assert index["state_compared"] == S_WORK
    failures = []
    for entry in index["cases"]:
        diff = compare_case(arrays, entry["id"])
        if diff["duties"] > RTOL or diff["states"] > RTOL or diff["case_mismatches"] > 0:
            failures.append(f"{entry['id']} {entry}: duties {diff['duties']:.3g}, states "
                            f"{diff['states']:.3g}, {int(diff['case_mismatches'])} case "
                            f"mismatches")
    assert not failures, "the step no longer computes what it did:\n" + "\n".join(failures)


def test_reference_covers_the_law(reference: tuple[dict[str, Any],
                                                  dict[str, np.ndarray]]) -> None:
    """The file holds every case of tests/law_reference.py, in full, and between them they
    cover every variant and option of the law, two plants, two seeds and every Eq. (33) case."""
    index, arrays = reference
    entries = index["cases"]
    assert [{k: v for k, v in e.items() if k not in ("id", "samples", "cases_seen")}
            for e in entries] == [c.describe() for c in reference_cases()]

    law_variants = {*VARIANTS, "original_darc/model"}
    assert set(LAW_VARIANTS) == law_variants
    assert {e["variant"] for e in entries} == law_variants
    assert {e["pwm_update"] for e in entries} == set(PWM_UPDATE_MODES)
    assert {e["dead_zone"] for e in entries} == set(DEAD_ZONE_MODES)
    assert {e["position_feedback"] for e in entries} == set(POSITION_FEEDBACK)
    assert len({e["plant"] for e in entries}) >= 2
    assert len({e["seed"] for e in entries}) >= 2
    assert {e["scenario"] for e in entries if e["variant"] == "modified_darc"} == set(
        GROUPS["all"])
    for variant in law_variants:
        assert len({e["scenario"] for e in entries if e["variant"] == variant}) >= 2, variant

    seen: set[int] = set()
    for e in entries:
        cid = e["id"]
        cfg, meas = arrays[f"{cid}/cfg"], arrays[f"{cid}/meas"]
        variant, _, accel = e["variant"].partition("/")
        assert cfg.shape == (CFG_SIZE,)
        # the stored config is the one the index describes
        assert (cfg[CFG_VARIANT], cfg[CFG_POS_FB], cfg[CFG_DZ_MODE]) == (
            VARIANTS.index(variant), POSITION_FEEDBACK.index(e["position_feedback"]),
            DEAD_ZONE_MODES.index(e["dead_zone"])), cid
        if variant == "original_darc":
            assert cfg[CFG_ORIG_ACCEL] == ORIGINAL_DARC_ACCEL.index(accel or "filtered"), cid
        n = round(DURATION / cfg[CFG_TS])
        assert meas.shape == (n, MEAS_SIZE) and e["samples"] == n, cid
        assert arrays[f"{cid}/duties"].shape == (n, 4), cid
        assert arrays[f"{cid}/state0"].shape == (STATE_SIZE,), cid
        assert np.array_equal(arrays[f"{cid}/state_rows"], state_rows(n)), cid
        assert arrays[f"{cid}/states"].shape == (len(state_rows(n)), STATE_SIZE), cid
        cases = arrays[f"{cid}/case"]
        assert cases.shape == (n,), cid
        seen |= {int(c) for c in cases}
    assert seen == {1, 2, 3, 4, 5}
