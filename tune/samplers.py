"""The study's sampler: TPE (default), or CMA-ES warm-started from a TPE phase (``--sampler``).

* ``tpe``: Optuna's multivariate TPE with :data:`N_STARTUP_TRIALS` random start-up trials and
  ``constant_liar=True`` (so that parallel workers do not all sample the same point). This is
  what every study ran before the option existed, with the same seed: unchanged results.
* ``cmaes``: the same TPE sampler (same seed, so the same trials) until the study holds
  :data:`CMAES_WARM_START` complete trials; then Optuna's ``CmaEsSampler`` with those first
  complete trials as ``source_trials`` (Warm Starting CMA-ES, Nomura et al. 2021: the initial
  mean and covariance are those of the best 10 % of the TPE trials, in the [0, 1]-scaled log
  space). Plain ``CmaEsSampler(n_startup_trials=N, independent_sampler=TPESampler(...))`` would
  *not* be a warm start: its CMA-ES starts from the middle of the box with sigma = 1/6 of it and
  ignores the start-up trials. Pruned trials are given to CMA-ES with their last reported value
  (``consider_pruned_trials=True``): CMA-ES ranks, and a candidate that went unstable (reported
  1000) or was pruned as worse than the median must rank low; without them a generation of 11
  would need ~18 trials at the objective's pruning rate. Needs the ``cmaes`` package
  (``pip install 'pneutune[cmaes]'``).
* ``gp`` (library only, for ``benchmarks/samplers.py``): Optuna's ``GPSampler``; needs torch.

Every sampler is seeded with :func:`pneutune.tune.study.sampler_seed`, as before.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import optuna
from optuna.distributions import BaseDistribution
from optuna.samplers import BaseSampler
from optuna.trial import FrozenTrial, TrialState

from pneutune.control.errors import PneutuneError, argument_error

#: Samplers ``tune --sampler`` offers (``gp`` is accepted by the library, for the benchmark).
SAMPLERS = ("tpe", "cmaes")
LIBRARY_SAMPLERS = (*SAMPLERS, "gp")
DEFAULT_SAMPLER = "tpe"
#: TPE start-up (random) trials.
N_STARTUP_TRIALS = 10
#: Complete trials sampled by TPE before CMA-ES takes over (``cmaes``); its source trials.
CMAES_WARM_START = 25
#: How to install what a sampler needs.
_NEEDS = {"cmaes": ("cmaes", "pip install 'pneutune[cmaes]' (or: pip install cmaes)"),
          "gp": ("torch", "pip install torch (CPU wheel, ~190 MB)")}


class SamplerError(PneutuneError, ValueError):
    """An unknown sampler, or one whose package is not installed."""


def check_sampler(name: str, library: bool = True) -> None:
    """Check that ``name`` is a sampler and that its package imports.

    Parameters
    ----------
    name : str
    library : bool
        Accept the library-only samplers (``gp``) too.

    Raises
    ------
    SamplerError
        Unknown name, or the package it needs is missing (the message says how to install it).
    """
    known = LIBRARY_SAMPLERS if library else SAMPLERS
    if name not in known:
        raise argument_error(SamplerError, "sampler",
                             f"must be one of {', '.join(known)}, got {name!r}")
    if name in _NEEDS:
        module, how = _NEEDS[name]
        try:
            __import__(module)
        except ImportError:
            raise argument_error(SamplerError, "sampler", f"{name} needs the {module} package, "
                                 f"which is not installed: {how}") from None


def tpe(seed: int) -> optuna.samplers.TPESampler:
    """The default sampler (module docstring)."""
    # multivariate is Optuna 5's default for one objective and False before it: set it, so that
    # a seed gives the same study under every Optuna the package accepts (Optuna 4 warns that
    # the option is experimental)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=N_STARTUP_TRIALS,
                                          multivariate=True, constant_liar=True)


class TpeThenCmaEsSampler(BaseSampler):
    """TPE until the study holds ``warm_start`` complete trials, then warm-started CMA-ES.

    Parameters
    ----------
    seed : int
        Seed of both samplers.
    warm_start : int, optional
        Complete trials sampled by TPE (default :data:`CMAES_WARM_START`, at least 10: the warm
        start takes the best 10 %); the first ``warm_start`` of them (by trial number) are
        CMA-ES's ``source_trials``, so a resumed study rebuilds the same start (and once CMA-ES
        has run, it restores its state from the study rather than from the source trials).
    """

    def __init__(self, seed: int, warm_start: int | None = None) -> None:
        warm_start = CMAES_WARM_START if warm_start is None else warm_start
        if warm_start < 10:  # the warm start takes the best 10 %: at least one trial
            raise SamplerError(f"warm_start >= 10 must hold, got {warm_start}")
        self._seed = int(seed)
        self._warm_start = int(warm_start)
        self._tpe = tpe(self._seed)
        self._cma: optuna.samplers.CmaEsSampler | None = None
        self._active: BaseSampler = self._tpe

    @property
    def phase(self) -> str:
        """``tpe`` or ``cmaes``: which sampler the current trial uses."""
        return "cmaes" if self._active is self._cma else "tpe"

    def _choose(self, study: optuna.Study) -> BaseSampler:
        if self._cma is None:
            complete = sorted(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)),
                              key=lambda t: t.number)
            if len(complete) < self._warm_start:
                return self._tpe
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                self._cma = optuna.samplers.CmaEsSampler(
                    seed=self._seed, source_trials=complete[:self._warm_start],
                    independent_sampler=self._tpe, consider_pruned_trials=True,
                    warn_independent_sampling=False)
        return self._cma

    def before_trial(self, study: optuna.Study, trial: FrozenTrial) -> None:
        self._active = self._choose(study)
        self._active.before_trial(study, trial)

    def infer_relative_search_space(self, study: optuna.Study,
                                    trial: FrozenTrial) -> dict[str, BaseDistribution]:
        return self._active.infer_relative_search_space(study, trial)

    def sample_relative(self, study: optuna.Study, trial: FrozenTrial,
                        search_space: dict[str, BaseDistribution]) -> dict[str, Any]:
        return self._active.sample_relative(study, trial, search_space)

    def sample_independent(self, study: optuna.Study, trial: FrozenTrial, param_name: str,
                           param_distribution: BaseDistribution) -> Any:
        return self._active.sample_independent(study, trial, param_name, param_distribution)

    def after_trial(self, study: optuna.Study, trial: FrozenTrial, state: TrialState,
                    values: Sequence[float] | None) -> None:
        self._active.after_trial(study, trial, state, values)

    def reseed_rng(self) -> None:
        self._tpe.reseed_rng()
        if self._cma is not None:
            self._cma.reseed_rng()


def make_sampler(name: str, seed: int) -> BaseSampler:
    """The sampler ``name`` seeded with ``seed`` (module docstring).

    Raises
    ------
    SamplerError
        Unknown name or missing package.
    """
    check_sampler(name)
    if name == "tpe":
        return tpe(seed)
    if name == "cmaes":
        return TpeThenCmaEsSampler(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.GPSampler(seed=seed, n_startup_trials=N_STARTUP_TRIALS,
                                         deterministic_objective=True)


def describe(name: str) -> str:
    """One line for report.md."""
    return {"tpe": f"TPE (multivariate, {N_STARTUP_TRIALS} random start-up trials)",
            "cmaes": f"CMA-ES warm-started from the first {CMAES_WARM_START} complete TPE "
                     "trials (before them: TPE)",
            "gp": f"Gaussian process (Optuna GPSampler, {N_STARTUP_TRIALS} random start-up "
                  "trials)"}[name]


__all__ = ["CMAES_WARM_START", "DEFAULT_SAMPLER", "LIBRARY_SAMPLERS", "N_STARTUP_TRIALS",
           "SAMPLERS", "SamplerError", "TpeThenCmaEsSampler", "check_sampler", "describe",
           "make_sampler", "tpe"]
