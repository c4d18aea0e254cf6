"""GA-LQR tuning for the comprehensive mode (paper §5.3, Eq. (39)-(44)).

A real-coded genetic algorithm (DEAP) searches the LQR output weights q1, q2, q3 (on BA, SWS,
DTD; genes are log10 q). Each individual is scored exactly: the LQR is designed on the relative
model (blind to the unobservable common mode, like every ECU gain) and the RMS ratios to the
passive car come from the continuous Lyapunov equation on the full model, D road at 20 m/s (the
ratios do not depend on the grade). Fitness: Eq. (43), the sum of the three ratios, under
Eq. (44) with a design margin (each ratio <= its bound), violations penalised. The bound
follows the vehicle: each ratio at most ``DesignOptions.comprehensive_bound`` and at most
exp(-z sigma), sigma the scatter of that ratio over a drive of ``ratio_window_s`` at the
tuned gain (``calib.model.window_bound``; as the safety design's BA): a ratio then stays
below 1 on such a drive with z sigma confidence, and no further margin is taken where the
car does not scatter (the SUV with its spring x0.7: the Eq. (43) optimum has BA 0.964 and
DTD 0.981, and a fixed 0.95 cost it 0.080 of the sum).
``python -m tools.tune_ga_lqr`` runs it and writes the gains file the ECU loads.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import random

import numpy as np
from deap import algorithms, base, creator, tools
from deap.tools import crossover as deap_crossover
from deap.tools import mutation as deap_mutation
from deap.tools import selection as deap_selection

from calib import grid
from calib.iso8608 import GRADE_GQ_M3
from calib.linear import RelativeFamily
from calib.model import linear_model, window_bound
from calib.options import NOMINAL_SPEED_MPS, DesignOptions


def vehicle_digest(cfg) -> str:
    """SHA-256 of the [vehicle] table's five values: the key of a gains file."""
    v = cfg.vehicle
    text = json.dumps([v.sprung_mass_kg, v.unsprung_mass_kg, v.spring_stiffness_n_per_m,
                       v.damping_n_s_per_m, v.tire_stiffness_n_per_m])
    return hashlib.sha256(text.encode()).hexdigest()


GENE_LO, GENE_HI = -3.0, 5.0
POPULATION = 40
GENERATIONS = 35
PENALTY = 100.0
WINDOW_STEPS = 4          # the bound's fixed point (sigma hardly moves with the bound)
WINDOW_TOL = 5e-4

if not hasattr(creator, "FitnessMinEq43"):
    creator.create("FitnessMinEq43", base.Fitness, weights=(-1.0,))
    creator.create("IndividualEq43", list, fitness=creator.FitnessMinEq43)


def tune(cfg, seed: int = 0, bound=None, population: int = POPULATION,
         generations: int = GENERATIONS, opts: DesignOptions | None = None) -> dict:
    """The GA-LQR for ``cfg``: the gains file's content. ``bound``: Eq. (44)'s bound per
    output [BA, SWS, DTD]; None: the design's own (see the module's doc), from ``opts``."""
    model = linear_model(cfg.vehicle, GRADE_GQ_M3["D"], NOMINAL_SPEED_MPS)
    fam = RelativeFamily(model)

    def run(b) -> dict:
        rng = random.Random(seed)
        with _own_random(random.Random(seed)):
            return _tune(cfg, np.asarray(b, float), model, fam, rng, seed, population,
                         generations)

    if bound is not None:
        return run(bound)
    opts = opts or DesignOptions()
    cap = np.asarray(opts.comprehensive_bound, float)
    b = cap.copy()
    for _ in range(WINDOW_STEPS):
        result = run(b)
        top = np.minimum(cap, window_bound(model, np.asarray(result["K"]), opts))
        ratios = np.array([result["ratios"][k] for k in ("ba", "sws", "dtd")])
        result["window_bound"] = top.tolist()
        if np.all(ratios <= top + WINDOW_TOL):
            return result
        b = np.minimum(b, top)
    result["feasible"], result["fitness"] = False, math.inf
    return result


# the modules whose operators draw from the module-level ``random`` generator
_DEAP_MODULES = (algorithms, deap_crossover, deap_mutation, deap_selection)


@contextlib.contextmanager
def _own_random(gen: random.Random):
    """DEAP's operators draw from the global ``random`` generator, which other threads of the
    process share (a Dask worker's event loop draws from it while the task runs: the same
    case then got other gains, and another trace, on each run). Inside, they draw from
    ``gen`` (seeded as ``random.seed(seed)`` seeded the global one: the same draws, alone)."""
    saved = [m.random for m in _DEAP_MODULES]
    for m in _DEAP_MODULES:
        m.random = gen
    try:
        yield
    finally:
        for m, r in zip(_DEAP_MODULES, saved):
            m.random = r


def _tune(cfg, bound, model, fam, rng, seed, population, generations) -> dict:

    def score(ind) -> tuple[float]:
        try:
            _, ratios = fam.evaluate(10.0 ** np.asarray(ind))
        except ValueError:
            return (math.inf,)
        # (on the grid: two individuals whose scores differ by rounding alone tie exactly,
        # and DEAP's tournaments and hall of fame break ties by order, the same on every host)
        return (grid.snap(float(np.sum(ratios)
                                + PENALTY * np.sum(np.maximum(ratios - bound, 0.0)))),)

    def clamp(ind):
        for i, g in enumerate(ind):
            ind[i] = min(GENE_HI, max(GENE_LO, g))
        return ind

    tb = base.Toolbox()
    tb.register("attr", rng.uniform, GENE_LO, GENE_HI)
    tb.register("individual", tools.initRepeat, creator.IndividualEq43, tb.attr, 3)
    tb.register("population", tools.initRepeat, list, tb.individual)
    tb.register("evaluate", score)
    tb.register("mate", tools.cxBlend, alpha=0.4)
    tb.register("mutate", tools.mutGaussian, mu=0.0, sigma=0.4, indpb=0.4)
    tb.register("select", tools.selTournament, tournsize=3)
    pop = tb.population(n=population)
    hof = tools.HallOfFame(1)
    evaluations = 0
    for ind in pop:
        ind.fitness.values = tb.evaluate(ind)
        evaluations += 1
    hof.update(pop)
    for _ in range(generations):
        offspring = algorithms.varAnd(pop, tb, cxpb=0.7, mutpb=0.3)
        for ind in offspring:
            clamp(ind)
            if not ind.fitness.valid:
                ind.fitness.values = tb.evaluate(ind)
                evaluations += 1
        hof.update(offspring)
        pop = tb.select(offspring, len(pop) - 1) + [tb.clone(hof[0])]   # elitism
    best = list(hof[0])
    q = 10.0 ** np.asarray(best)
    K, ratios = fam.evaluate(q)
    feasible = bool(np.all(ratios <= bound + 1e-9))
    return {
        "generator": "tools.tune_ga_lqr", "seed": seed, "population": population,
        "generations": generations, "evaluations": evaluations,
        "vehicle": cfg.source, "vehicle_sha256": vehicle_digest(cfg),
        "bound": bound.tolist(), "q": q.tolist(), "K": K.tolist(),
        "fitness": float(np.sum(ratios)) if feasible else math.inf, "feasible": feasible,
        "ratios": {"ba": float(ratios[0]), "sws": float(ratios[1]), "dtd": float(ratios[2])},
        "state": ["zs_dot", "zt_dot", "zs", "zt", "zf"], "law": "u = -K x (N)",
    }
