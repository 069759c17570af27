"""The paper's controller that ``tune`` compares against: on a rig other than the paper's, its
file with the model's rig and limits blocks (the recipe docs/commissioning.md gives a user),
not the paper's geometry run on another plant."""

from __future__ import annotations

from pneutune.control.contracts.controller import PAPER_CONTROLLER, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.api import paper_on_rig
from pneutune.tune.space import controller_from_params, search_space

#: A 63 mm bore with a 100 mm stroke (rod 20 mm), sampled every 5 ms with 100 Hz PWM.
OTHER = {"rig": {"A_a": 3.117e-3, "A_b": 2.803e-3, "x_min": 0.0, "x_max": 0.1, "Ts": 0.005,
                 "pwm_hz": 100.0}}


def _tuned(plant: PlantConfig):
    model = model_from_plant(plant)
    return controller_from_params(model, search_space(model).paper_params())


def test_on_the_papers_rig_the_file_is_the_baseline() -> None:
    """The default plant is the paper's rig: the file itself, unchanged."""
    paper = load_controller(PAPER_CONTROLLER)
    base, moved = paper_on_rig(paper, _tuned(PlantConfig()))
    assert not moved
    assert base is paper


def test_on_another_rig_the_baseline_takes_its_rig_and_limits() -> None:
    """Another bore, stroke, Ts and PWM frequency: the baseline has the tuned controller's rig
    and limits and keeps every other block of the paper's file (gains, adaptation, filters,
    valves, PWM curve)."""
    paper = load_controller(PAPER_CONTROLLER)
    tuned = _tuned(PlantConfig().with_updates(OTHER))
    base, moved = paper_on_rig(paper, tuned)
    assert moved
    assert base.rig == tuned.rig and base.limits == tuned.limits
    assert base.rig.Ts == 0.005 and base.limits.x_max == tuned.limits.x_max
    for block in ("gains", "adaptation", "kalman", "valves", "pwm", "variant"):
        assert getattr(base, block) == getattr(paper, block), block
