"""ISO 8608 road generation in distance, routes and their file format."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.config import ConfigError
from hil.sim.road import (GRADE_GQ_M3, GRADES, RoadSettings, Route, constant_route, drive_timeline,
                      estimate_gq, generate_profile, grade_of, load_route, make_segment,
                      shipped_routes)

ROOT = Path(__file__).resolve().parents[1]


def long_route(grade: str, convention: str = "iso", length_m: float = 20000.0) -> Route:
    seg = make_segment(grade, length_m=length_m, speed_mps=20.0)
    return Route("t", (seg,), RoadSettings(convention=convention, dx_m=0.05))


@pytest.mark.parametrize("grade", list(GRADES))
def test_welch_psd_matches_grade_iso(grade):
    est = estimate_gq(generate_profile(long_route(grade), seed=GRADES.index(grade)))
    assert est == pytest.approx(GRADE_GQ_M3[grade], rel=0.10)


def test_paper_convention_doubles_the_psd():
    iso = estimate_gq(generate_profile(long_route("B", "iso"), seed=7))
    paper = estimate_gq(generate_profile(long_route("B", "paper"), seed=7))
    assert paper / iso == pytest.approx(2.0, rel=1e-9)  # same draws, sqrt(2) amplitude
    assert paper == pytest.approx(2 * GRADE_GQ_M3["B"], rel=0.10)


def test_any_gq_allowed():
    seg = make_segment(gq_m3=1.0e-4, length_m=20000.0, speed_mps=15.0)
    assert seg.grade == "B"
    est = estimate_gq(generate_profile(Route("g", (seg,), RoadSettings(dx_m=0.05)), seed=3))
    assert est == pytest.approx(1.0e-4, rel=0.10)


def test_same_seed_same_bytes_different_seed_different_profile():
    route = load_route("full_road_section")
    a = generate_profile(route, seed=11).heights_m
    b = generate_profile(route, seed=11).heights_m
    c = generate_profile(route, seed=12).heights_m
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, c)
    assert abs(np.corrcoef(a, c)[0, 1]) < 0.5


def test_road_is_a_function_of_distance_not_speed():
    slow = Route("s", (make_segment("C", length_m=300.0, speed_mps=10.0),
                       make_segment("A", length_m=300.0, speed_mps=12.0)))
    fast = Route("f", (make_segment("C", length_m=300.0, speed_mps=30.0),
                       make_segment("A", length_m=300.0, speed_mps=25.0)))
    assert np.array_equal(generate_profile(slow, 5).heights_m, generate_profile(fast, 5).heights_m)


def test_profile_continuous_across_segment_boundaries():
    # D next to A: the step at the boundary is no larger than the steps inside D
    route = Route("b", tuple(make_segment(g, length_m=200.0, speed_mps=20.0) for g in "DADA"))
    prof = generate_profile(route, seed=2)
    steps = np.abs(np.diff(prof.heights_m))
    typical = np.quantile(steps[: int(200 / prof.dx_m)], 0.999)
    for boundary in route.boundaries_m()[1:-1]:
        i = int(round(boundary / prof.dx_m))
        assert steps[i - 2:i + 2].max() <= typical


def test_grade_of_bands():
    assert grade_of(GRADE_GQ_M3["C"]) == "C"
    assert grade_of(GRADE_GQ_M3["C"] * 1.99) == "C"
    assert grade_of(GRADE_GQ_M3["C"] * 2.0) == "D"
    assert grade_of(1e-9) == "A" and grade_of(1.0) == "H"


def test_timeline_covers_route():
    route = load_route("full_road_section")
    tl = drive_timeline(route, 0.001)
    assert np.all(np.diff(tl.x_m) > 0)
    assert tl.x_m[0] == 0.0
    assert route.length_m - 0.031 < tl.x_m[-1] < route.length_m
    assert len(tl) == pytest.approx(route.duration_s / 0.001, abs=len(route.segments) + 1)
    # the speed is the segment's
    for i, seg in enumerate(route.segments):
        assert np.all(tl.speed_mps[tl.segment == i] == seg.speed_mps)


def test_shipped_routes_load_and_full_section_has_a_to_d_at_several_speeds():
    names = shipped_routes()
    assert "full_road_section" in names
    for name in names:
        assert load_route(name).segments
    route = load_route("full_road_section")
    grades = [s.grade for s in route.segments]
    assert {"A", "B", "C", "D"} <= set(grades)
    assert grades[0] == grades[-1] == "A"
    assert len({s.speed_mps for s in route.segments}) >= 3


def test_constant_route_duration():
    r = constant_route("B", 20.0, 30.0)
    assert r.duration_s == pytest.approx(30.0)
    with pytest.raises(ValueError):
        constant_route("Z", 20.0, 30.0)


ROUTE_OK = '[[segment]]\ngrade = "B"\nlength_m = 100.0\nspeed_mps = 20.0\n'
BAD_ROUTES = [
    ("no segments", 'name = "x"\n', "segment"),
    ("missing length", '[[segment]]\ngrade = "B"\nspeed_mps = 20.0\n', "segment[0].length_m"),
    ("both grade and gq", '[[segment]]\ngrade = "B"\ngq_m3 = 1e-5\nlength_m = 1.0\nspeed_mps = 2.0\n', "exactly one"),
    ("neither", '[[segment]]\nlength_m = 1.0\nspeed_mps = 2.0\n', "exactly one"),
    ("bad grade", ROUTE_OK.replace('"B"', '"Q"'), "segment[0].grade"),
    ("negative length", ROUTE_OK.replace("100.0", "-100.0"), "segment[0].length_m"),
    ("nan speed", ROUTE_OK.replace("20.0", "nan"), "segment[0].speed_mps"),
    ("too fast", ROUTE_OK.replace("20.0", "500.0"), "segment[0].speed_mps"),
    ("unknown key", ROUTE_OK + "slope = 3\n", "segment[0].slope"),
    ("bad convention", '[road]\nconvention = "din"\n' + ROUTE_OK, "road.convention"),
    ("broken", ROUTE_OK + "[[segment\n", "invalid TOML"),
]


@pytest.mark.parametrize("desc,text,word", BAD_ROUTES, ids=[c[0] for c in BAD_ROUTES])
def test_bad_route_file_gives_clear_error(tmp_path, desc, text, word):
    path = tmp_path / "r.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_route(path)
    assert word in str(exc.value) and str(path) in str(exc.value)
    assert "\n" not in str(exc.value)


def test_unknown_route_name_lists_shipped():
    with pytest.raises(ConfigError, match="full_road_section"):
        load_route("no_such_route")


def test_route_file_gq_and_convention(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text('[road]\nconvention = "paper"\ncutoff_n_per_m = 0.01\n'
                    '[[segment]]\ngq_m3 = 3e-4\nlength_m = 50.0\nspeed_mps = 10\n')
    r = load_route(path)
    assert r.road.convention == "paper" and r.road.cutoff_n_per_m == 0.01
    assert r.segments[0].grade == "C" and r.segments[0].gq_m3 == 3e-4


def test_cli_bad_route_exits_2(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text(ROUTE_OK.replace('"B"', '"Q"'))
    proc = subprocess.run([sys.executable, "-m", "hil", "drive", "--route", str(path), "--json"],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and "segment[0].grade" in proc.stderr


def test_noise_is_continuous_in_time_at_constant_speed():
    """At constant speed the distance-domain process is Eq. (1): check the lag-1 correlation
    of the height at the plant step against the OU value exp(-2 pi f0 dt)."""
    r = long_route("C", length_m=4000.0)
    h = generate_profile(r, seed=9).heights_m
    rho = np.corrcoef(h[:-1], h[1:])[0, 1]
    assert rho == pytest.approx(math.exp(-2 * math.pi * r.road.cutoff_n_per_m * r.road.dx_m), abs=1e-3)
