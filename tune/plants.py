"""Simulated plants drawn from the identified model's uncertainty (deterministic, seeded).

The nominal plant is the model read as a plant.yaml: rig, mass, Stribeck friction, valves (C, b,
delays, minimum pulse), leak, sensor noise, and the constant disturbances F_n, D_a, D_b at θ's
nominal values. For ``model_from_plant(PlantConfig())`` it equals ``PlantConfig()``.

Draws (``draw_plants``), all sharing the nominal's rig, delays, leak and sensors:

* draw 0: the nominal plant;
* draw 1 (``slow``): the corner where the valves deliver least and the load asks most -- every
  valve at C_min, b_max; mass, F_C, F_S, b_v at their maxima; F_n at its maximum, D_a at its
  minimum, D_b at its maximum; v_s and alpha nominal;
* draw 2 (``fast``): the opposite corner -- C_max, b_min, the lightest, least damped plant
  (the one an aggressive gain set destabilises);
* draws 3.. (``lhs-k``): a scrambled Latin hypercube over the whole box (uniform per coordinate).

The box of each coordinate and the nominal plant: :mod:`pneutune.control.sim.model_box`.

Each draw carries its own sensor-noise seed in ``sim.seed``: draw 0 uses the study seed itself
(so ``simulate --plant plant-nominal.yaml`` or ``--seed S`` repeats the objective's nominal runs),
draw k the first word of ``SeedSequence([seed, k])``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.stats import qmc

from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.model_box import (
    Coordinate,
    corner,
    nominal_plant,
    plant_from_values,
    uncertainty_box,
)


@dataclass(frozen=True)
class PlantDraw:
    """One sampled plant.

    Attributes
    ----------
    index : int
        0 is the nominal plant.
    label : str
        ``nominal``, ``slow``, ``fast`` or ``lhs-<k>``.
    plant : PlantConfig
        The plant, its ``sim.seed`` the draw's sensor-noise seed.
    values : dict
        The sampled coordinates (key path -> value).
    """

    index: int
    label: str
    plant: PlantConfig
    values: dict[str, float]

    @property
    def noise_seed(self) -> int:
        """Sensor-noise seed of this draw (``plant.sim.seed``)."""
        return self.plant.sim.seed


def draw_seed(seed: int, index: int) -> int:
    """Sensor-noise seed of draw ``index`` (module docstring)."""
    if index == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def draw_plants(model: ModelConfig, n_draws: int, seed: int,
                box: Mapping[str, tuple[float, float]] | None = None) -> tuple[PlantDraw, ...]:
    """``n_draws`` plants from the model's uncertainty (module docstring), deterministic in seed.

    Parameters
    ----------
    model : ModelConfig
    n_draws : int
        Number of plants, >= 1 (1: the nominal only; 3: nominal and the two corners).
    seed : int
        Seed of the Latin hypercube and of the sensor noise (>= 0).
    box : mapping, optional
        Narrower ranges (:func:`uncertainty_box`).

    Returns
    -------
    tuple of PlantDraw
    """
    if n_draws < 1:
        raise ValueError(f"n_draws >= 1 must hold, got {n_draws}")
    coords = uncertainty_box(model, box)
    draws = [PlantDraw(0, "nominal", nominal_plant(model, draw_seed(seed, 0)),
                       {c.key: c.nominal for c in coords})]

    specs: list[tuple[str, dict[str, float]]] = []
    if n_draws >= 2:
        specs.append(("slow", corner(coords, slow=True)))
    if n_draws >= 3:
        specs.append(("fast", corner(coords, slow=False)))
    n_lhs = n_draws - 1 - len(specs)
    if n_lhs > 0:
        sampler = qmc.LatinHypercube(d=len(coords), rng=np.random.default_rng([int(seed), 7]))
        unit = sampler.random(n_lhs)
        for k in range(n_lhs):
            specs.append((f"lhs-{k + 1}", {c.key: c.low + unit[k, j] * (c.high - c.low)
                                           for j, c in enumerate(coords)}))
    for i, (label, values) in enumerate(specs, start=1):
        plant = plant_from_values(model, values, draw_seed(seed, i), label)
        draws.append(PlantDraw(i, label, plant, values))
    return tuple(draws)


__all__ = ["Coordinate", "PlantDraw", "draw_plants", "draw_seed", "nominal_plant",
           "plant_from_values", "uncertainty_box"]
