"""GA-LQR tuning for the comprehensive mode (paper §5.3, Eq. (39)-(44)).

A real-coded genetic algorithm (DEAP) searches the LQR output weights q1, q2, q3 (on BA, SWS,
DTD; genes are log10 q). Each individual is scored exactly: the LQR is designed on the relative
model (blind to the unobservable common mode, like every ECU gain) and the RMS ratios to the
passive car come from the continuous Lyapunov equation on the full model, D road at 20 m/s (the
ratios do not depend on the grade). Fitness: Eq. (43), the sum of the three ratios, under
Eq. (44) with a design margin (each ratio <= its bound), violations penalised.

    python -m tools.tune_ga_lqr [--vehicle F] [--seed N] [--simulate SECONDS] [--out FILE] --json

writes the gains file the ECU loads (default: hil/gains/galqr_<vehicle digest>.json).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
from pathlib import Path

import numpy as np
from deap import algorithms, base, creator, tools

from hil.cli import add_json_argument, add_vehicle_argument, emit, positive_float, seed_arg, vehicle_or_exit
from hil.config import VehicleConfig
from hil.ecu_params import DesignOptions, NOMINAL_SPEED_MPS, vehicle_digest, default_gains_path
from hil.model import linear_model
from hil.road import GRADE_GQ_M3
from tools.linear import RelativeFamily

GENE_LO, GENE_HI = -3.0, 5.0
POPULATION = 40
GENERATIONS = 35
PENALTY = 100.0

if not hasattr(creator, "FitnessMinEq43"):
    creator.create("FitnessMinEq43", base.Fitness, weights=(-1.0,))
    creator.create("IndividualEq43", list, fitness=creator.FitnessMinEq43)


def tune(cfg: VehicleConfig, seed: int = 0, bound=None, population: int = POPULATION,
         generations: int = GENERATIONS) -> dict:
    bound = np.asarray(bound if bound is not None else DesignOptions().comprehensive_bound, float)
    model = linear_model(cfg.vehicle, GRADE_GQ_M3["D"], NOMINAL_SPEED_MPS)
    fam = RelativeFamily(model)
    rng = random.Random(seed)
    random.seed(seed)  # DEAP's operators draw from the global generator

    def score(ind) -> tuple[float]:
        try:
            _, ratios = fam.evaluate(10.0 ** np.asarray(ind))
        except ValueError:
            return (math.inf,)
        return (float(np.sum(ratios) + PENALTY * np.sum(np.maximum(ratios - bound, 0.0))),)

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


def confirm_by_simulation(cfg: VehicleConfig, K: list, seconds: float, seed: int) -> dict:
    """Time-domain confirmation: the whole ECU in the loop (SIL), comprehensive mode, D road."""
    import tempfile

    from hil import sil
    from hil.road import constant_route

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gains.json"
        path.write_text(json.dumps({"K": K, "vehicle_sha256": vehicle_digest(cfg)}))
        rep, _ = sil.run(cfg, constant_route("D", NOMINAL_SPEED_MPS, seconds + sil.SETTLE_S),
                         "comprehensive", seed, gains_file=path)
    r = rep["segments"][0]["ratio"]
    return {"seconds": seconds, "seed": seed, "ratios": r, "fitness": sum(r.values())}


def write_gains(result: dict, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    keep = {k: v for k, v in result.items() if k not in ("vehicle", "simulation", "gains_file")}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(keep, indent=2) + "\n")
    tmp.replace(path)
    return path


def _render(o: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"GA-LQR (seed {o['seed']}, {o['evaluations']} evaluations)")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    t.add_row("q (BA, SWS, DTD)", ", ".join(f"{x:.4g}" for x in o["q"]))
    t.add_row("K (zs', zt', zs, zt, zf)", ", ".join(f"{x:.1f}" for x in o["K"]))
    r = o["ratios"]
    t.add_row("ratios BA / SWS / DTD", f"{r['ba']:.4f} / {r['sws']:.4f} / {r['dtd']:.4f}")
    t.add_row("fitness, Eq. (43)", f"{o['fitness']:.4f}")
    if "simulation" in o:
        s = o["simulation"]
        t.add_row(f"SIL {s['seconds']:g} s fitness", f"{s['fitness']:.4f}")
    t.add_row("gains file", o["gains_file"])
    Console().print(t)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.tune_ga_lqr", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_vehicle_argument(parser)
    add_json_argument(parser)
    parser.add_argument("--seed", type=seed_arg, default=0)
    parser.add_argument("--simulate", type=positive_float, metavar="SECONDS",
                        help="confirm the result by a SIL simulation this long")
    parser.add_argument("--out", metavar="FILE", help="gains file to write "
                        "(default: hil/gains/galqr_<vehicle digest>.json)")
    args = parser.parse_args(argv)
    cfg = vehicle_or_exit(args.vehicle)
    result = tune(cfg, args.seed)
    if not result["feasible"]:
        print("error: the GA found no weights satisfying Eq. (44) with the design margin",
              file=sys.stderr)
        return 1
    path = write_gains(result, Path(args.out) if args.out else default_gains_path(cfg))
    result["gains_file"] = str(path)
    if args.simulate:
        result["simulation"] = confirm_by_simulation(cfg, result["K"], args.simulate, args.seed)
    emit(result, args.json, _render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
