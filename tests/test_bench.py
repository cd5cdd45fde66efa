"""kneas-bench: grid expansion, aggregation (hand-written metrics.json fixtures), resume, backends, CLI."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import pytest

from kneas_method.bench import aggregate, backends, estimate, grid, paper_results
from kneas_method.bench.cells import cell_dir, find_metrics, is_complete, run_cell
from kneas_method.bench.grid import REFERENCE_METHODS, Cell
from kneas_method.errors import KneasError

# A stand-in for kneas-train: same arguments, same run-folder layout, metrics that depend on the cell.
FAKE_TRAIN = r'''
import json, os, sys, pathlib
args = sys.argv[1:]
def opt(name):
    return args[args.index(name) + 1] if name in args else None
if args[0] == "--resume":  # an interrupted run finished in its own folder
    if os.environ.get("FAKE_LOG"):
        with open(os.environ["FAKE_LOG"], "a") as f:
            f.write(json.dumps({"args": args}) + "\n")
    run = pathlib.Path(args[1])
    (run / "metrics.json").write_text(json.dumps({"psnr2d": 1.0, "ssim2d": 0.9, "psnr3d": 1.0, "ssim3d": 0.8, "psnr3d_ls": 1.0,
        "parameters": 1, "steps": 2, "wall_time_s": 0.5, "preset": "tiny", "scene_source": "built-in phantom foot"}))
    sys.exit(0)
method = args[0]
scene, out, seed = opt("--scene"), pathlib.Path(opt("--output-dir")), int(opt("--seed"))
k = int(opt("--num-materials")) if opt("--num-materials") else {"neas-1m": 1, "neas-2m": 2}.get(method)
if os.environ.get("FAKE_LOG"):
    with open(os.environ["FAKE_LOG"], "a") as f:
        f.write(json.dumps({"args": args, "cuda": os.environ.get("CUDA_VISIBLE_DEVICES"), "omp": os.environ.get("OMP_NUM_THREADS")}) + "\n")
stop = os.environ.get("FAKE_STOP")  # "scene/method/k/seed": checkpoint, then the table is stopped (SIGTERM to kneas-bench)
if stop and stop == f"{scene}/{method}/{k}/{seed}":
    import signal, time
    run = out / scene / method / "20240101-000009"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.json").write_text("{}")
    (run / "checkpoints" / "step-00000010.ckpt").write_bytes(b"x")
    os.kill(os.getppid(), signal.SIGTERM)
    time.sleep(60)
fail = os.environ.get("FAKE_FAIL")
if fail and fail == f"{scene}/{method}/{k}/{seed}":
    print("Traceback (most recent call last):\nRuntimeError: boom in " + fail, file=sys.stderr)
    sys.exit(3)
run = out / scene / method / ("20240101-00000" + str(seed))
run.mkdir(parents=True)
base = {"neas-1m": 40.0, "neas-2m": 41.0, "k-neas": 42.0, "fdk": 30.0}.get(method, 35.0) + (k or 0) * 0.1 + seed
(run / "config.json").write_text(json.dumps({"method": method, "scene": scene, "views": opt("--views"), "seed": seed, "num_materials": k}))
metrics = {"psnr2d": base, "ssim2d": 0.9, "psnr3d": base - 10, "ssim3d": 0.8, "psnr3d_ls": base - 9,
    "parameters": 1, "steps": 2, "wall_time_s": 0.5, "preset": opt("--preset"), "scene_source": "built-in phantom " + scene}
if "--trace" in args:  # an oracle run: its best count 1 dB above the last
    n = int(opt("--reconstruction.iterations"))
    metrics["trace"] = {"psnr3d": [base - 10] * n, "best": {"iterations": n // 2, "psnr3d": base - 9, "ssim3d": 0.85}}
(run / "metrics.json").write_text(json.dumps(metrics))
'''


@pytest.fixture()
def fake_prefix(tmp_path):
    script = tmp_path / "fake_train.py"
    script.write_text(FAKE_TRAIN)
    return (sys.executable, str(script))


def _calls(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


# ---------------------------------------------------------------------------- grids


CLASSICAL = ("fdk", "sart", "os-sart", "cgls", "asd-pocs")


def test_reference_methods_are_the_classical_kneas_train_methods():
    from kneas_method import registry
    from kneas_method.classical.options import ALGORITHMS
    from kneas_method.methods import ClassicalConfig

    assert REFERENCE_METHODS == ALGORITHMS and set(REFERENCE_METHODS) == set(CLASSICAL)
    specs = registry.methods()
    assert all(isinstance(specs[m].config, ClassicalConfig) for m in REFERENCE_METHODS)
    assert all(grid.is_reference(m) for m in CLASSICAL) and not any(grid.is_reference(m) for m in ("naf", "k-neas", "neas-1m"))
    # classical methods have no materials and train no prior
    assert set(CLASSICAL) <= set(grid.NO_MATERIALS) and set(CLASSICAL) <= set(estimate.PRIOR_METHODS_NO)
    grid.check_methods(CLASSICAL)


def test_table1_grid_matches_the_paper_layout():
    cells = grid.table1(["foot", "jaw"], grid.seeds_from_count(2), "tiny")
    # per scene: NeAS 1M, 2M + K-NeAS 1M..4M = 6 configs x 2 seeds, + one run per classical reference
    assert len(cells) == 2 * (6 * 2 + 5)
    assert len({c.id for c in cells}) == len(cells)
    foot = [c for c in cells if c.scene == "foot"]
    assert sorted((c.method, c.k) for c in foot if c.seed == 0 and c.method not in CLASSICAL) == [
        ("k-neas", 1), ("k-neas", 2), ("k-neas", 3), ("k-neas", 4), ("neas-1m", 1), ("neas-2m", 2)]
    assert {c.seed for c in foot if c.method not in CLASSICAL} == {0, 1}
    refs = [c for c in foot if c.method in CLASSICAL]
    assert sorted(c.method for c in refs) == sorted(CLASSICAL)  # each classical reference once per scene
    assert all(c.k is None and c.seed == 0 and c.views is None for c in refs)
    assert all("--num-materials" not in c.train_args("o") and c.train_args("o")[:3] == [c.method, "--scene", "foot"] for c in refs)
    # the references can be chosen, or left out
    assert not [c for c in grid.table1(["foot"], (0, 1), "tiny", references=()) if c.method in CLASSICAL]
    only = grid.table1(["foot", "jaw"], (0, 1), "tiny", references=("cgls", "sart"))
    assert sorted((c.scene, c.method) for c in only if c.method in CLASSICAL) == [
        ("foot", "cgls"), ("foot", "sart"), ("jaw", "cgls"), ("jaw", "sart")]
    with pytest.raises(KneasError, match="unknown reference method"):
        grid.table1(["foot"], (0,), "tiny", references=("naf",))

    by = {(c.method, c.k, c.seed): c for c in foot}
    out = Path("/o/cells/x")
    assert by[("k-neas", 3, 1)].train_args(out) == ["k-neas", "--scene", "foot", "--num-materials", "3", "--seed", "1",
                                                     "--preset", "tiny", "--output-dir", "/o/cells/x"]
    # neas-1m / neas-2m have fixed K: no --num-materials; fdk has none either
    assert "--num-materials" not in by[("neas-1m", 1, 0)].train_args(out)
    assert "--num-materials" not in by[("neas-2m", 2, 0)].train_args(out)
    assert by[("fdk", None, 0)].train_args(out)[:3] == ["fdk", "--scene", "foot"]
    # ids are deterministic and folder-safe
    assert by[("k-neas", 2, 0)].id == "foot__k-neas__K2__vall__s0__tiny"
    assert Cell("data/foot_50.pickle", "k-neas", 2, None, 0, "tiny").id.startswith("foot_50-")


def test_views_and_ablation_grids():
    cells = grid.views_table(["chest"], (0, 1, 2), "cpu")
    learned = [c for c in cells if c.method not in CLASSICAL]
    assert len(learned) == 4 * 3 * 3
    assert {c.views for c in learned} == {5, 10, 20, 50}
    # K = 2 as the paper's table, and k-neas as a user runs it (no K given: no --num-materials)
    assert {(c.method, c.k) for c in learned} == {("neas-2m", 2), ("k-neas", 2), ("k-neas", None)}
    assert all("--num-materials" not in c.train_args("o") for c in learned if c.k is None)
    assert {(c.method, c.k) for c in grid.views_table(["chest"], (0,), "cpu", found_k=False) if c.method not in CLASSICAL} == {
        ("neas-2m", 2), ("k-neas", 2)}
    for m in CLASSICAL:  # every reference once per view count, seed 0
        refs = [c for c in cells if c.method == m]
        assert sorted(c.views for c in refs) == [5, 10, 20, 50] and {c.seed for c in refs} == {0}
    assert "--views" in [a for c in cells if c.method == "asd-pocs" for a in c.train_args("o")]
    assert len(cells) == 4 * 3 * 3 + 4 * 5
    assert grid.views_table(["chest"], (0,), "cpu", references=()) == [c for c in grid.views_table(["chest"], (0,), "cpu")
                                                                        if c.method not in CLASSICAL]
    assert "--views" in learned[0].train_args("o") and "--num-materials" in [a for c in learned if c.method == "k-neas" for a in c.train_args("o")]

    ab = grid.ablation(["foot"], (0,), "cpu")
    assert [c.method for c in ab] == ["kselector", "kselector-floater", "kselector-shared", "k-neas", *CLASSICAL]
    assert all(c.k == 2 for c in ab if c.method not in CLASSICAL)
    assert all(c.train_args("o")[3:5] == ["--num-materials", "2"] for c in ab if c.method not in CLASSICAL)
    assert all(c.k is None and c.seed == 0 for c in ab if c.method in CLASSICAL)
    # a classical method given as a variant is a reference: one run, no K
    ab = grid.ablation(["foot"], (0, 1), "cpu", methods=("k-neas", "sart"), references=())
    assert [(c.method, c.k, c.seed) for c in ab] == [("k-neas", 2, 0), ("k-neas", 2, 1), ("sart", None, 0)]


def test_generic_grid_and_validation():
    cells = grid.grid(["foot"], ["k-neas", "neas-2m", "naf", "fdk", "os-sart"], (2, 3), (10, None), (0, 1), "tiny")
    methods = [(c.method, c.k, c.views, c.seed) for c in cells]
    assert sum(m == "k-neas" for m, *_ in methods) == 2 * 2 * 2
    assert sum(m == "neas-2m" for m, *_ in methods) == 2 * 2  # K fixed at 2
    assert all(k is None for m, k, *_ in methods if m in ("naf", "fdk", "os-sart"))
    assert sum(m == "naf" for m, *_ in methods) == 2 * 2
    for ref in ("fdk", "os-sart"):  # once per view count, seed 0
        assert sorted((v or 0, seed) for m, _, v, seed in methods if m == ref) == [(0, 0), (10, 0)]
    with pytest.raises(KneasError, match="number of seeds"):
        grid.seeds_from_count(0)
    with pytest.raises(KneasError, match="unknown preset"):
        grid.table1(["foot"], (0,), "fast")
    with pytest.raises(KneasError, match="unknown method"):
        grid.check_methods(["k-neas", "nope"])
    # extra kneas-train arguments change the cell identity
    assert Cell("foot", "k-neas", 2, None, 0, "tiny", ("--trainer.epochs", "5")).id != Cell("foot", "k-neas", 2, None, 0, "tiny").id


def test_paper_numbers_typed_in_exactly():
    t1 = paper_results.TABLE1
    assert t1["Abdomen"]["3M"]["K-NeAS"] == {"psnr2d": 47.687, "ssim2d": 0.994, "psnr3d": 33.276, "ssim3d": 0.858}
    assert t1["Jaw"]["1M"]["NeAS"] == {"psnr2d": 39.451, "ssim2d": 0.966, "psnr3d": 34.099, "ssim3d": 0.882}
    assert "NeAS" not in t1["Chest"]["4M"]
    assert sum(len(models) for rows in t1.values() for models in rows.values()) == 4 * 6
    assert paper_results.TABLE2[10]["K-NeAS"]["psnr3d"] == 24.486
    assert paper_results.TABLE3["K-Selector + Shared Body"] == {"psnr2d": 42.544, "ssim2d": 0.981, "psnr3d": 31.245, "ssim3d": 0.883}
    assert paper_results.paper_value("foot", "k-neas", 2, None, "psnr2d") == 42.570  # Table 1 first
    assert paper_results.paper_value("foot", "k-neas", 2, None, "psnr2d", table="ablation") == 43.245
    assert paper_results.paper_value("data/chest_50.pickle", "neas-2m", 2, 5, "ssim2d") == 0.899
    assert paper_results.paper_value("foot", "neas-1m", 2, None, "psnr2d") is None
    assert paper_results.paper_value("mine", "k-neas", 2, None, "psnr2d") is None
    # The paper's numbers apply only to its own scenes; its claims about an anatomy are checked on ours too.
    assert paper_results.paper_value("ts-chest.pickle", "k-neas", 2, 5, "psnr3d") is None
    assert [paper_results.scene_key(s) for s in ("Foot", "data/jaw_50.pickle", "ts-chest.pickle")] == ["Foot", "Jaw", None]
    assert paper_results.scene_key("/data/ts-chest.pickle", same_anatomy=True) == "Chest"
    assert paper_results.scene_key("head.pickle", same_anatomy=True) is None


# ---------------------------------------------------------------------------- aggregation (hand-written fixtures)


def _write_metrics(out: Path, cell: Cell, values: dict, source: str, stamp: str = "20240101-000000") -> None:
    run = cell_dir(out, cell) / Path(cell.scene).stem / cell.method / stamp
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"method": cell.method, "scene": cell.scene, "views": cell.views, "seed": cell.seed,
                                                 "num_materials": cell.k}))
    metrics = {"parameters": 1, "steps": 10, "wall_time_s": 3.0, "preset": "tiny", "scene_source": source, **values}
    (run / "metrics.json").write_text(json.dumps(metrics))


def _m(p2, s2, p3, s3):
    return {"psnr2d": p2, "ssim2d": s2, "psnr3d": p3, "ssim3d": s3, "psnr3d_ls": p3 + 1}


def test_table1_aggregation_mean_std_bold_paper_and_references(tmp_path):
    cells = grid.table1(["foot", "jaw"], (0, 1), "tiny", ks=(1, 2, 3))
    public = "public benchmark data/foot_50.pickle"
    fixtures = {
        ("foot", "neas-1m", 1): [_m(40.0, 0.90, 30.0, 0.80), _m(42.0, 0.92, 31.0, 0.82)],
        ("foot", "neas-2m", 2): [_m(41.0, 0.91, 30.5, 0.85), _m(41.0, 0.91, 30.5, 0.85)],
        ("foot", "k-neas", 1): [_m(39.0, 0.95, 29.0, 0.70), _m(39.5, 0.95, 29.0, 0.70)],
        ("foot", "k-neas", 2): [_m(43.0, 0.93, 32.0, 0.81), _m(44.0, 0.93, 33.0, 0.81)],
        ("foot", "k-neas", 3): [_m(42.0, 0.94, 31.0, 0.81)],  # seed 1 failed
        ("foot", "fdk", None): [_m(50.0, 0.99, 40.0, 0.99)],  # the references are never bold, even when best
        ("foot", "sart", None): [_m(55.0, 0.98, 41.0, 0.98)],
        ("foot", "cgls", None): [_m(45.0, 0.97, 35.0, 0.97)],  # os-sart and asd-pocs never ran: rows with "—"
        ("jaw", "neas-1m", 1): [_m(30.0, 0.8, 20.0, 0.7), _m(30.0, 0.8, 20.0, 0.7)],
    }
    for c in cells:
        vals = fixtures.get((c.scene, c.method, c.k))
        if vals and c.seed < len(vals):
            _write_metrics(tmp_path, c, vals[c.seed], public if c.scene == "foot" else "built-in phantom jaw (cached)")
    failed = next(c for c in cells if (c.scene, c.method, c.k, c.seed) == ("foot", "k-neas", 3, 1))
    cell_dir(tmp_path, failed).mkdir(parents=True)
    (cell_dir(tmp_path, failed) / "cell.json").write_text(json.dumps({"status": "failed", "error": "boom"}))

    table, groups, paths = aggregate.write_tables(tmp_path, "table1", cells)
    g = groups[("foot", "neas-1m", 1, None)]
    assert g.mean("psnr2d") == pytest.approx(41.0) and g.std("psnr2d") == pytest.approx(2 ** 0.5)  # sample std
    assert groups[("foot", "k-neas", 3, None)].failed == 1

    md = paths[0].read_text()
    assert paths[0].name == "table1.md" and paths[1].name == "table1.csv"
    lines = {tuple(x.strip() for x in line.strip("|").split("|")[:2]): line for line in md.splitlines() if line.startswith("| ")}
    header = md.splitlines()[2]
    assert "2D PSNR NeAS | 2D PSNR NeAS (paper) | 2D PSNR K-NeAS | 2D PSNR K-NeAS (paper)" in header
    row1 = [x.strip() for x in lines[("foot", "1M")].strip("|").split("|")]
    # Scene, Config, 2D PSNR: NeAS, NeAS paper, K-NeAS, K-NeAS paper, 2D SSIM: ...
    assert row1[2] == "41.000 ± 1.414" and row1[3] == "42.230"
    assert row1[4] == "39.250 ± 0.354" and row1[5] == "42.717"
    assert row1[8] == "**0.950 ± 0.000**"  # best 2D SSIM of foot
    row2 = [x.strip() for x in lines[("foot", "2M")].strip("|").split("|")]
    assert row2[4] == "**43.500 ± 0.707**"  # best 2D PSNR of foot
    assert row2[10] == "30.500 ± 0.000" and row2[11] == "31.092"
    assert row2[12] == "**32.500 ± 0.707**" and row2[13] == "31.388"
    row3 = [x.strip() for x in lines[("foot", "3M")].strip("|").split("|")]
    assert row3[2] == "—" and row3[3] == "—"  # NeAS has no 3M
    assert row3[4] == "42.000 (n=1/2)" and row3[5] == "42.800"
    fdk = [x.strip() for x in lines[("foot", "FDK (ref.)")].strip("|").split("|")]
    assert fdk[2] == "50.000" and "**" not in lines[("foot", "FDK (ref.)")]
    sart = [x.strip() for x in lines[("foot", "SART (ref.)")].strip("|").split("|")]
    assert sart[2] == "55.000" and sart[4] == "—" and "**" not in lines[("foot", "SART (ref.)")]
    assert [x.strip() for x in lines[("foot", "CGLS (ref.)")].strip("|").split("|")][2] == "45.000"
    assert [x.strip() for x in lines[("foot", "OS-SART (ref.)")].strip("|").split("|")][2] == "—"
    # one row per classical reference, after the scene's K rows, in REFERENCE_METHODS order
    configs = [key[1] for key in lines if key[0] == "foot"]
    assert configs == ["1M", "2M", "3M", "FDK (ref.)", "SART (ref.)", "OS-SART (ref.)", "CGLS (ref.)", "ASD-POCS (ref.)"]
    assert [key[1] for key in lines if key[0] == "jaw"][3:] == configs[3:]
    assert "classical references FDK, SART, OS-SART, CGLS, ASD-POCS" in md
    # jaw is a built-in phantom: no paper numbers beside ours, and a note says why
    jaw1 = [x.strip() for x in lines[("jaw", "1M")].strip("|").split("|")]
    assert jaw1[2] == "**30.000 ± 0.000**" and jaw1[3] == "—"
    jaw2 = [x.strip() for x in lines[("jaw", "2M")].strip("|").split("|")]
    assert jaw2[2] == "—"  # never run
    assert "jaw: built-in synthetic phantom" in md
    # a scene file of the user's own is neither the public benchmark nor a built-in phantom
    own = {("knee.pickle", "k-neas", 2, None): aggregate.Group(("knee.pickle", "k-neas", 2, None), sources={"file knee.pickle"}),
           ("jaw", "k-neas", 2, None): aggregate.Group(("jaw", "k-neas", 2, None), sources={"built-in phantom jaw"})}
    notes = aggregate._source_note(own, ["knee.pickle", "jaw"], False)
    assert notes[0].startswith("jaw: built-in synthetic phantom") and notes[1].startswith("knee.pickle: scene file(s) of their own")

    import csv

    rows = list(csv.DictReader(paths[1].open()))
    foot1 = next(r for r in rows if r["scene"] == "foot" and r["config"] == "1M")
    assert float(foot1["psnr2d_neas_mean"]) == pytest.approx(41.0) and float(foot1["psnr2d_neas_std"]) == pytest.approx(2 ** 0.5)
    assert foot1["psnr2d_neas_n"] == "2" and foot1["psnr2d_kneas_paper"] == "42.717"
    assert float(foot1["psnr3d_ls_neas_mean"]) == pytest.approx(31.5)
    assert {r["config"]: r["reference"] for r in rows if r["scene"] == "foot"} == {
        "1M": "0", "2M": "0", "3M": "0", "FDK (ref.)": "1", "SART (ref.)": "1", "OS-SART (ref.)": "1", "CGLS (ref.)": "1",
        "ASD-POCS (ref.)": "1"}
    assert float(next(r for r in rows if r["scene"] == "foot" and r["config"] == "SART (ref.)")["psnr2d_neas_mean"]) == pytest.approx(55.0)
    per_cell = list(csv.DictReader(paths[2].open()))
    assert len(per_cell) == len(cells)
    assert next(r for r in per_cell if r["cell_id"] == failed.id)["status"] == "failed"


def test_views_and_ablation_layouts(tmp_path):
    cells = grid.views_table(["chest"], (0,), "tiny", views=(5, 10))
    for c in cells:
        base = {"neas-2m": 30.0, "k-neas": 31.0, "fdk": 20.0, "sart": 40.0, "os-sart": 41.0, "cgls": 42.0, "asd-pocs": 43.0}[c.method] + c.views
        found = c.method == "k-neas" and c.k is None  # K from the bounds: the run records the K it found
        values = {**_m(base - 0.5, 0.9, base - 10.5, 0.5), "num_materials": 3} if found else _m(base, 0.9, base - 10, 0.5)
        _write_metrics(tmp_path, c, values, "public benchmark data/chest_50.pickle")
    _, _, paths = aggregate.write_tables(tmp_path, "views", cells)
    md = paths[0].read_text()
    row5 = next(line for line in md.splitlines() if line.startswith("| chest | 5 |"))
    parts = [x.strip() for x in row5.strip("|").split("|")]
    assert parts[2:6] == ["35.000", "30.473", "**36.000**", "30.813"]  # better model at this view count in bold
    assert any(line.startswith("| chest | 10 FDK (ref.) |") for line in md.splitlines())
    assert "| chest | 5 K-NeAS, K found (K = 3) | — | — | 35.500 | — |" in md  # no paper value: the paper fixes K = 2
    # every classical reference at every view count; never bold even where it beats both models
    for label, base in (("FDK", 20.0), ("SART", 40.0), ("OS-SART", 41.0), ("CGLS", 42.0), ("ASD-POCS", 43.0)):
        for v in (5, 10):
            assert f"| chest | {v} {label} (ref.) | {base + v:.3f} |" in md
    assert "| chest | 5 ASD-POCS (ref.) | 48.000 | — | — | — |" in md
    assert not [line for line in md.splitlines() if "(ref.)" in line and "**" in line]

    ab = grid.ablation(["foot"], (0,), "tiny")
    for i, c in enumerate(ab):
        _write_metrics(tmp_path / "ab", c, _m(40.0 + i, 0.9, 30.0, 0.8), "public benchmark data/foot_50.pickle")
    _, _, paths = aggregate.write_tables(tmp_path / "ab", "ablation", ab)
    md = paths[0].read_text()
    assert "| foot | K-Selector + Floater Reg | kselector-floater | 2 | 41.000 | 43.115 |" in md
    assert "| foot | K-NeAS | k-neas | 2 | **43.000** | 43.245 |" in md
    assert "| foot | FDK (ref.) | fdk | — | 44.000 | — |" in md
    for i, m in enumerate(CLASSICAL):  # ablation cells: the four variants, then the references in order
        assert f"| foot | {m.upper()} (ref.) | {m} | — | {44.0 + i:.3f} | — |" in md
    assert "**48.000**" not in md  # asd-pocs has the highest 2D PSNR, but bold stays with the learned models


def test_grid_layout_marks_classical_methods_as_references(tmp_path):
    cells = grid.grid(["foot"], ["k-neas", "naf", "cgls", "sart"], (2,), (None,), (0, 1), "tiny")
    assert [(c.method, c.seed) for c in cells] == [("k-neas", 0), ("k-neas", 1), ("naf", 0), ("naf", 1), ("cgls", 0), ("sart", 0)]
    for c in cells:
        base = {"k-neas": 40.0, "naf": 38.0, "cgls": 50.0, "sart": 45.0}[c.method] + c.seed
        _write_metrics(tmp_path, c, _m(base, 0.9, base - 10, 0.8), "built-in phantom foot")
    _, _, paths = aggregate.write_tables(tmp_path, "grid", cells)
    md = paths[0].read_text()
    assert "| foot | k-neas | 2 | all | **40.500 ± 0.707** |" in md and "| foot | cgls | — | all | 50.000 |" in md
    import csv

    assert {r["method"]: r["reference"] for r in csv.DictReader(paths[1].open())} == {"k-neas": "0", "naf": "0", "cgls": "1", "sart": "1"}
    assert "classical references SART, CGLS" in md


# ---------------------------------------------------------------------------- running, resume, failures


def test_resume_skips_complete_cells_and_records_failures(tmp_path, fake_prefix, monkeypatch):
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setenv("FAKE_FAIL", "foot/k-neas/2/1")
    out = tmp_path / "bench"
    cells = grid.table1(["foot"], (0, 1), "tiny", ks=(1, 2))
    assert len(cells) == 4 * 2 + 5  # {neas-1m, neas-2m, k-neas 1M, 2M} x 2 seeds + 5 classical references
    # one cell is already complete from an earlier run: it must not be trained again
    _write_metrics(out, cells[0], _m(1, 1, 1, 1), "built-in")
    # a helper run's metrics (the NeAS-1M prior of an interrupted k-neas run) do not make a cell complete
    prior = cell_dir(out, cells[1]) / "foot" / "neas-1m-prior" / "abc123"
    prior.mkdir(parents=True)
    (prior / "metrics.json").write_text("{}")
    assert cells[1].method == "k-neas" and not is_complete(out, cells[1])
    seen = []
    results = backends.LocalBackend(workers=1).run([c for c in cells if not is_complete(out, c)], out, fake_prefix,
                                                   on_result=lambda c, r: seen.append((c.id, r.status)))
    assert len(_calls(log)) == 12 and len(seen) == 12
    failed = [r for r in results if r.status == "failed"]
    assert [r.cell_id for r in failed] == ["foot__k-neas__K2__vall__s1__tiny"]
    record = json.loads((out / "cells" / failed[0].cell_id / "cell.json").read_text())
    assert record["status"] == "failed" and record["returncode"] == 3 and "boom in foot/k-neas/2/1" in record["error"]
    assert "train.log" in os.listdir(out / "cells" / failed[0].cell_id)
    done = json.loads((cell_dir(out, cells[1]) / "cell.json").read_text())
    assert done["status"] == "done" and Path(done["run_dir"]).joinpath("metrics.json").is_file() and done["wall_time_s"] > 0

    # rerun: only the failed cell runs
    monkeypatch.delenv("FAKE_FAIL")
    log.unlink()
    todo = [c for c in cells if not is_complete(out, c)]
    assert [c.id for c in todo] == [failed[0].cell_id]
    results = backends.LocalBackend().run(todo, out, fake_prefix)
    assert [r.status for r in results] == ["done"] and len(_calls(log)) == 1
    # and a third time nothing; run_cell itself also refuses to redo a complete cell
    assert not [c for c in cells if not is_complete(out, c)]
    assert run_cell(cells[3], out, fake_prefix).status == "skipped"
    assert len(_calls(log)) == 1


def test_an_interrupted_cell_resumes_its_run(tmp_path, fake_prefix, monkeypatch):
    """A cell stopped after a checkpoint continues that run (kneas-train --resume), not a new one."""
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    out = tmp_path / "bench"
    cell = next(c for c in grid.table1(["foot"], (0,), "tiny", ks=(2,)) if c.method == "k-neas")
    stopped = cell_dir(out, cell) / "foot" / "k-neas" / "20240101-000000"
    (stopped / "checkpoints").mkdir(parents=True)
    (stopped / "config.json").write_text("{}")
    (stopped / "checkpoints" / "step-00000020.ckpt").write_bytes(b"x")
    other = cell_dir(out, cell) / "foot" / "neas-1m-prior" / "abc"  # a helper run's folder is not the cell's run
    other.mkdir(parents=True)
    result = run_cell(cell, out, fake_prefix)
    (call,) = _calls(log)
    assert call["args"] == ["--resume", str(stopped)]
    assert result.status == "done" and result.run_dir == str(stopped)
    assert json.loads((cell_dir(out, cell) / "cell.json").read_text())["resumed"] == str(stopped)
    # without a checkpoint there is nothing to resume: a fresh run
    fresh = next(c for c in grid.table1(["foot"], (1,), "tiny", ks=(2,)) if c.method == "k-neas")
    bare = cell_dir(out, fresh) / "foot" / "k-neas" / "20231231-235959"
    bare.mkdir(parents=True)
    (bare / "config.json").write_text("{}")
    assert run_cell(fresh, out, fake_prefix).status == "done"
    assert _calls(log)[-1]["args"][0] == "k-neas"


def test_local_workers_get_one_gpu_each_or_share_the_cpus(tmp_path, fake_prefix, monkeypatch):
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cells = grid.grid(["foot"], ["k-neas"], (1, 2, 3, 4), (None,), (0,), "tiny")
    results = backends.LocalBackend(workers=2, gpus=["0", "1"]).run(cells, tmp_path / "g", fake_prefix)
    assert sorted(r.status for r in results) == ["done"] * 4
    assert {c["cuda"] for c in _calls(log)} <= {"0", "1"} and len(_calls(log)) == 4
    log.unlink()
    cpu = backends.LocalBackend(workers=2, gpus=[])
    cpu.run(grid.grid(["jaw"], ["k-neas"], (2,), (None,), (0, 1), "tiny"), tmp_path / "c", fake_prefix)
    expected = str(max(1, backends.cpu_count() // 2))
    assert [c["cuda"] for c in _calls(log)] == [None, None] and {c["omp"] for c in _calls(log)} == {expected}


def test_missing_trainer_is_a_recorded_failure(tmp_path):
    cell = Cell("foot", "k-neas", 2, None, 0, "tiny")
    r = run_cell(cell, tmp_path, (sys.executable, str(tmp_path / "does_not_exist.py")))
    assert r.status == "failed" and r.returncode != 0 and "does_not_exist.py" in r.error
    assert find_metrics(cell_dir(tmp_path, cell)) is None


def test_ray_missing_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(KneasError, match=r"pip install 'kneas\[distributed\]'"):
        backends.make_backend("ray")


# ---------------------------------------------------------------------------- CLI


def test_cli_runs_a_table_then_trains_nothing(tmp_path, fake_prefix, monkeypatch, capsys):
    from kneas_method.cli import bench as cli

    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setattr(cli, "TRAIN_PREFIX", fake_prefix)
    out = tmp_path / "bench"
    argv = ["ablation", "--preset", "tiny", "--seeds", "2", "--output-dir", str(out)]
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 0
    calls = _calls(log)
    assert len(calls) == 4 * 2 + 5 + 2  # 4 variants x 2 seeds + each classical reference once + the SART and ASD-POCS oracles
    oracle_calls = [c["args"] for c in calls if "--trace" in c["args"]]
    assert sorted(a[0] for a in oracle_calls) == ["asd-pocs", "sart"]
    assert all(a[a.index("--reconstruction.iterations") + 1] == "40" for a in oracle_calls)
    assert sorted(c["args"][0] for c in calls if c["args"][0] in CLASSICAL and "--trace" not in c["args"]) == sorted(CLASSICAL)
    assert all("--num-materials" not in c["args"] and c["args"][c["args"].index("--seed") + 1] == "0"
               for c in calls if c["args"][0] in CLASSICAL)
    md = (out / "table3_ablation.md").read_text()
    assert "| foot | K-NeAS | k-neas | 2 | **42.700 ± 0.707** |" in md  # fake metrics: 42 + 0.1 K + seed
    assert "| foot | FDK (ref.) | fdk | — | 30.000 |" in md and "| foot | OS-SART (ref.) | os-sart | — | 35.000 |" in md
    assert "| foot | ASD-POCS best of 1-40 (oracle) | asd-pocs@best | — | — | — | 26.000 | 0.850 |" in md  # the trace's best
    assert (out / "table3_ablation.csv").is_file()
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 0 and len(_calls(log)) == 15  # nothing trained again
    assert "15 already complete, 0 to run" in capsys.readouterr().out


def test_archive_keeps_the_records_the_page_reads_and_a_table_continues_from_it(tmp_path, fake_prefix, monkeypatch, capsys):
    from kneas_method.bench import page
    from kneas_method.cli import bench as cli

    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setattr(cli, "TRAIN_PREFIX", fake_prefix)
    out, kept, elsewhere = tmp_path / "bench", tmp_path / "kept", tmp_path / "elsewhere"
    with pytest.raises(SystemExit) as exc:
        cli.main(["ablation", "--preset", "tiny", "--seeds", "1", "--references", "fdk", "--oracles", "--output-dir", str(out)])
    assert exc.value.code == 0
    first = next((out / "cells").iterdir())
    volume = next(first.glob("*/*/*/")) / "volume.npy"  # what a real run leaves beside its records
    volume.write_bytes(b"\0" * 4096)
    running = out / "cells" / "foot__k-neas__K2__vall__s1__tiny"  # a cell of another sitting, still running
    (running / "foot" / "k-neas" / "20240101-000001").mkdir(parents=True)
    (running / "cell.json").write_text(json.dumps({"status": "running"}))
    (running / "foot" / "k-neas" / "20240101-000001" / "config.json").write_text("{}")
    stopped = out / "cells" / "foot__k-neas__K3__vall__s1__tiny"  # interrupted after its helper prior run finished
    (stopped / "foot" / "neas-1m-prior" / "abc").mkdir(parents=True)
    (stopped / "foot" / "neas-1m-prior" / "abc" / "metrics.json").write_text("{}")
    (stopped / "cell.json").write_text(json.dumps({"status": "interrupted", "cell": {"method": "k-neas"}}))
    with pytest.raises(SystemExit) as exc:
        cli.main(["archive", "--output-dir", str(out), "--to", str(kept)])
    assert exc.value.code == 0
    assert "archived 20 records of 5 cells" in capsys.readouterr().out  # cell.json, train.log, config.json, metrics.json
    assert not list(kept.rglob("*.npy")) and (kept / "ablation.cells.json").is_file() and not (kept / "cells" / running.name).exists()
    assert not (kept / "cells" / stopped.name).exists()  # an interrupted cell's partial records stay behind
    same = page.render(kept).split("\n", 3)[3].replace(str(kept), str(out))
    assert same == page.render(out).split("\n", 3)[3]  # the same tables, verdicts and counts
    # another machine: the records copied into a new working folder; the table runs only the cells it lacks
    with pytest.raises(SystemExit) as exc:
        cli.main(["archive", "--output-dir", str(kept), "--to", str(elsewhere)])
    assert exc.value.code == 0
    calls = len(_calls(log))
    with pytest.raises(SystemExit) as exc:
        cli.main(["ablation", "--preset", "tiny", "--seeds", "2", "--references", "fdk", "--oracles", "--output-dir", str(elsewhere)])
    assert exc.value.code == 0
    again = _calls(log)[calls:]
    assert sorted(c["args"][0] for c in again) == sorted(grid.ABLATION_METHODS) and {c["args"][c["args"].index("--seed") + 1] for c in again} == {"1"}
    # archiving the second sitting into the first's archive keeps both: the manifest is the union
    with pytest.raises(SystemExit) as exc:
        cli.main(["archive", "--output-dir", str(elsewhere), "--to", str(kept)])
    assert exc.value.code == 0
    assert "9 of 9 cells complete" in page.render(kept)
    # the page says which code the cells ran on (metrics.json's code record; the fake runs have none)
    record = next((kept / "cells").glob("*/*/kselector/*/metrics.json"))
    record.write_text(json.dumps({**json.loads(record.read_text()), "code": {"kneas": "0.1.0", "commit": "ab" * 20},
                                  "machine": {"processor": "Some CPU", "cores": 2, "torch": "2.13.0"}}))
    assert "9 of 9 cells complete, " in page.render(kept)
    assert ("; code: not recorded (8 cells), abababababab (1 cell); machines: not recorded (8 cells), "
            "Some CPU / 2 cores / torch 2.13.0 (1 cell).\n") in page.render(kept)
    # and when: the days its cells started on (cell.json), one cell set back to an earlier sitting
    cell_json = record.parents[3] / "cell.json"
    cell_json.write_text(json.dumps({**json.loads(cell_json.read_text()), "started": "2020-01-02T03:04:05"}))
    assert re.search(r"recorded run time; run 2020-01-02 to 20\d\d-\d\d-\d\d; code: ", page.render(kept))
    for bad in (["--output-dir", str(tmp_path / "nothing")], ["--output-dir", str(out), "--to", str(out)]):
        with pytest.raises(SystemExit) as exc:
            cli.main(["archive", *bad])
        assert exc.value.code != 0 and "Traceback" not in capsys.readouterr().err


def test_a_table_run_with_another_procedure_is_its_own_table_on_the_page(tmp_path, fake_prefix, monkeypatch, capsys):
    from kneas_method.bench import page
    from kneas_method.cli import bench as cli

    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setattr(cli, "TRAIN_PREFIX", fake_prefix)
    out, kept = tmp_path / "bench", tmp_path / "kept"
    base = ["ablation", "--preset", "tiny", "--seeds", "1", "--references", "fdk", "--oracles", "--output-dir", str(out)]
    for argv in (base, base + ["--procedure", "paper"]):
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert exc.value.code == 0
    calls = [c["args"] for c in _calls(log)]
    neural = [a for a in calls if a[0] in grid.ABLATION_METHODS]
    assert len(neural) == 8 and sum(a[-2:] == ["--procedure", "paper"] for a in neural) == 4  # the default's four, then the paper's
    assert [a[0] for a in calls].count("fdk") == 1  # the classical rows are the same run in both tables
    assert (out / "ablation@paper.cells.json").is_file() and (out / "table3_ablation@paper.md").is_file()
    assert (out / "table3_ablation.md").is_file()
    assert page.table_names(out) == ["ablation", "ablation@paper"]
    text = page.render(out)
    assert "## Table 3: component ablation\n" in text and "## Table 3: component ablation, the paper procedure" in text
    assert text.count("### Claims") == 2 and text.count("\n- **") == 8  # the four claims checked in each table
    with pytest.raises(SystemExit) as exc:
        cli.main(["archive", "--output-dir", str(out), "--to", str(kept)])
    assert exc.value.code == 0 and page.table_names(kept) == ["ablation", "ablation@paper"]
    capsys.readouterr()
    for bad in (base + ["--procedure", "papper"], base + ["--train-args=--procedure paper"]):
        with pytest.raises(SystemExit) as exc:
            cli.main(bad)
        err = capsys.readouterr().err
        assert exc.value.code != 0 and "procedure" in err and "Traceback" not in err
    assert grid.procedure_args(None) == () and Cell("foot", "k-neas", 2, None, 0, "tiny", ("--procedure", "paper")).id.endswith("__x" + __import__(
        "hashlib").sha1("--procedure\0paper".encode()).hexdigest()[:8])


def test_cli_references_option(tmp_path, fake_prefix, monkeypatch):
    from kneas_method.cli import bench as cli

    def refs(argv):
        return sorted({(c.method, c.views) for c in cli.expand(cli.parse_args(argv)) if c.method in CLASSICAL and not c.oracle})

    def oracles(argv):
        return sorted({(c.method, c.views) for c in cli.expand(cli.parse_args(argv)) if c.oracle})

    assert refs(["table1", "--scenes", "foot"]) == sorted((m, None) for m in CLASSICAL)  # default: all five
    assert refs(["table1", "--scenes", "foot", "--references"]) == []  # empty: none
    assert refs(["views", "--views", "5", "10", "--references", "sart", "cgls"]) == [("cgls", 5), ("cgls", 10), ("sart", 5), ("sart", 10)]
    assert refs(["ablation", "--references"]) == []
    assert refs(["grid", "--methods", "k-neas", "--references", "asd-pocs"]) == [("asd-pocs", None)]
    assert refs(["grid", "--methods", "k-neas", "cgls", "--references"]) == [("cgls", None)]  # a classical method asked for by name
    assert refs(["grid", "--methods", "k-neas"]) == sorted((m, None) for m in CLASSICAL)
    # the oracles: SART and ASD-POCS by default, per view count, whatever the references
    assert oracles(["views", "--views", "5", "10", "--references"]) == [("asd-pocs", 5), ("asd-pocs", 10), ("sart", 5), ("sart", 10)]
    assert oracles(["table1", "--scenes", "foot", "--oracles", "cgls"]) == [("cgls", None)]
    assert oracles(["grid", "--methods", "k-neas", "--oracles"]) == []
    with pytest.raises(KneasError, match="--oracles takes iterative classical methods"):
        oracles(["table1", "--oracles", "fdk"])

    # a run without references trains none and the table has no (ref.) rows
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setattr(cli, "TRAIN_PREFIX", fake_prefix)
    with pytest.raises(SystemExit) as exc:
        cli.main(["ablation", "--preset", "tiny", "--seeds", "1", "--references", "--oracles", "--output-dir", str(tmp_path / "b")])
    assert exc.value.code == 0
    assert [c["args"][0] for c in _calls(log)] == ["kselector", "kselector-floater", "kselector-shared", "k-neas"]
    md = (tmp_path / "b" / "table3_ablation.md").read_text()
    assert "(ref.)" not in md and "classical references" not in md and "(oracle)" not in md


def test_cli_dry_run_and_user_errors(tmp_path, capsys, monkeypatch):
    from kneas_method.cli import bench as cli

    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as exc:
        cli.main(["views", "--preset", "tiny", "--seeds", "1", "--dry-run", "--output-dir", str(tmp_path / "o")])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    # 4 view counts x {neas-2m, k-neas K = 2, k-neas K found} + 4 view counts x (5 classical references + 2 oracles)
    assert "40 of 40 cells to run" in out and "asd-pocs (best of 1-40)" in out and "steps x 0.04 s (tiny, cpu)" in out and "classical asd-pocs" in out
    assert not (tmp_path / "o").exists()  # a dry run creates nothing
    for argv, msg in ((["table1", "--seeds", "0"], "number of seeds"),
                      (["grid", "--methods", "nope"], "unknown method"),
                      (["table1", "--references", "naf"], "--references"),
                      (["table1", "--no-fdk"], "unknown option --no-fdk"),
                      (["table1", "--train-args=--seed 3"], "must not contain --seed"),
                      (["table1", "--workers", "2", "--backend", "ray"], "--workers is for the local backend"),
                      # refused in a dry run too: every cell would fail on them
                      (["table1", "--scenes", "nosuch", "--dry-run"], "--scenes 'nosuch' is neither an existing file"),
                      (["table1", "--scenes", "foot", "--views", "0", "--dry-run"], "view counts must be whole numbers >= 1, got 0"),
                      (["views", "--scenes", "foot", "--views", "5", "60", "--dry-run"],
                       "--views 60 is more than scene foot's 50 training views; choose counts from 1 to 50"),
                      (["table1", "--workers", "0", "--dry-run"], "--workers must be at least 1")):
        with pytest.raises(SystemExit) as exc:
            cli.main([*argv, "--output-dir", str(tmp_path / "e")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1


def test_dry_run_estimates_follow_the_machine_speed_and_cells_measured_here(tmp_path):
    import torch

    cells = grid.table1(["foot"], (0,), "cpu", ks=(2,), references=("sart",), extra=("--trainer.epochs", "1"), oracles=())
    neural = next(c for c in cells if c.method == "k-neas")  # one epoch: well inside the time budget
    sart = next(c for c in cells if c.method == "sart")
    base, _ = estimate.estimate(neural, "cpu", None, 1.0)
    half, how = estimate.estimate(neural, "cpu", None, 0.5)
    assert half == pytest.approx(0.5 * base) and "x 0.50 for this machine" in how
    cap, how = estimate.estimate(neural, "cpu", None, 100.0)  # a slow machine: the time budget (wall clock) caps a run
    assert cap < 100.0 * base and "capped by the time budget" in how
    assert estimate.estimate(sart, "cpu", None, 2.0)[0] == pytest.approx(2.0 * estimate.estimate(sart, "cpu", None, 1.0)[0])
    assert estimate.estimate(neural, "cpu", {estimate.measured_key(neural): 123.0}, 2.0) == (123.0, "measured here")
    # measured here: a cell's own wall time (start-up included) where it recorded one; an oracle apart from its method's default
    ref = grid.table1(["foot"], (0,), "cpu", ks=(2,), references=("sart",), oracles=("sart",))
    sart_ref, sart_oracle = (next(c for c in ref if c.method == "sart" and c.oracle == o) for o in (False, True))
    _write_metrics(tmp_path, sart_ref, _m(1, 1, 1, 1), "built-in phantom foot")  # metrics.json wall_time_s 3.0
    (cell_dir(tmp_path, sart_ref) / "cell.json").write_text(json.dumps({"status": "done", "wall_time_s": 8.0}))
    _write_metrics(tmp_path, sart_oracle, _m(1, 1, 1, 1), "built-in phantom foot")  # no cell.json: the run's 3.0
    measured = estimate.measured_here(tmp_path, ref)
    assert estimate.estimate(sart_ref, "cpu", measured)[0] == 8.0 and estimate.estimate(sart_oracle, "cpu", measured)[0] == 3.0
    threads = torch.get_num_threads()
    probe = estimate.probe_seconds(repeats=2)
    assert 0.0 < probe < 10.0 and torch.get_num_threads() == threads
    factor, how = estimate.machine_speed("cpu")
    assert factor > 0 and "CPU figures x" in how and estimate.machine_speed("gpu")[0] == 1.0


def test_table_note_says_when_there_is_one_seed():
    from kneas_method.bench.aggregate import _common_notes

    one = " ".join(_common_notes(grid.table1(["foot"], (0,), "tiny", ks=(2,))))
    assert "one seed (0): no spread" in one and "std" not in one
    three = " ".join(_common_notes(grid.table1(["foot"], (0, 1, 2), "tiny", ks=(2,))))
    assert "mean ± sample std over seeds 0, 1, 2" in three


def test_view_counts_above_a_scenes_training_views_are_refused_before_any_cell(tmp_path, monkeypatch):
    """A pickle's own count (here 4) is read; a built-in name's is its simulation's, without simulating it;
    a public benchmark pickle in ./data stands in for the built-in name, as kneas-train's --scene does."""
    from conftest import foot_scene_file

    from kneas_method.data.scenes import training_view_count

    path = foot_scene_file(tmp_path)
    assert training_view_count(path) == 4
    assert training_view_count("jaw") == 50
    cells = grid.grid([str(path)], ["k-neas"], views=(2, 4), seeds=(0,), preset="tiny")
    assert sorted(c.views for c in cells) == [2, 4]
    with pytest.raises(KneasError, match=r"--views 5 is more than scene .*foot_tiny.pickle's 4 training views; choose counts from 1 to 4"):
        grid.grid([str(path)], ["k-neas"], views=(2, 5), seeds=(0,), preset="tiny")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "jaw_50.pickle").write_bytes(path.read_bytes())
    assert training_view_count("jaw") == 4
    with pytest.raises(KneasError, match="--views 10 is more than scene jaw's 4 training views"):
        grid.views_table(["jaw"], (0,), "tiny", views=(5, 10))


# ---------------------------------------------------------------------------- the results page


def _page_lines(text: str, start: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(start)]


def test_results_page_from_fake_cells_has_the_papers_numbers_and_a_verdict_per_claim(tmp_path):
    from kneas_method.bench import page

    out = tmp_path / "bench"
    knee = tmp_path / "knee.pickle"  # a scene of an anatomy the paper does not have (only its name is read here)
    knee.write_bytes(b"")
    knee = str(knee)
    t1 = grid.table1(["abdomen", "jaw", knee], (0,), "cpu", ks=(1, 2, 3), references=("asd-pocs",))
    psnr = {("abdomen", "neas-1m", 1): 30.0, ("abdomen", "neas-2m", 2): 31.0, ("abdomen", "k-neas", 1): 31.5,
            ("abdomen", "k-neas", 2): 32.0, ("abdomen", "k-neas", 3): 33.0,  # K-NeAS above NeAS, best at K = 3: both hold
            ("jaw", "neas-1m", 1): 30.0, ("jaw", "neas-2m", 2): 30.1, ("jaw", "k-neas", 2): 31.0,  # paper: K-NeAS below on jaw
            (knee, "neas-1m", 1): 30.0, (knee, "k-neas", 2): 31.0}  # no knee in the paper
    for c in t1:
        if (c.scene, c.method, c.k) in psnr:
            _write_metrics(out, c, _m(40.0, 0.9, psnr[(c.scene, c.method, c.k)], 0.8), f"built-in phantom {c.scene}")
    page.add_to_manifest(out, "table1", t1)
    views = grid.views_table(["chest"], (0, 1), "cpu", views=(5, 50), references=("fdk", "asd-pocs"), oracles=("asd-pocs",))
    vals = {("neas-2m", 5): [20.0, 20.2], ("k-neas", 5): [22.0, 22.2], ("neas-2m", 50): [30.0, 31.0],
            ("k-neas", 50): [30.2, 30.8],  # 0.0 apart, std 0.57: within one std, not comparable
            ("asd-pocs", 5): [21.0], ("fdk", 5): [15.0], ("asd-pocs", 50): [29.0],
            ("asd-pocs@best", 5): [23.0], ("asd-pocs@best", 50): [30.1]}  # the oracle: the best count of a traced run
    for c in views:
        v = vals.get((c.group[1], c.views))
        if v and c.seed < len(v):
            values = _m(40.0, 0.9, v[c.seed], 0.7 if c.method == "asd-pocs" else 0.8)
            if c.method == "k-neas" and c.k is None:  # K found: 1 dB above K = 2, above the oracle at 5 views
                values = {**_m(40.0, 0.9, v[c.seed] + 1.0, 0.8), "num_materials": 4}
            if c.oracle:  # metrics.json's own figures are the last count's; the trace has the best
                values = {**_m(40.0, 0.9, 1.0, 0.1), "trace": {"psnr3d": [1.0, v[c.seed]], "best": {"iterations": 2, "psnr3d": v[c.seed],
                                                                                                   "ssim3d": 0.7}}}
            _write_metrics(out, c, values, "built-in phantom chest")
    page.add_to_manifest(out, "views", views)
    path = page.write_page(out, tmp_path / "docs" / "paper_tables.md")
    text = path.read_text()
    assert "do not edit by hand" in text and "## Table 3: component ablation" in text
    assert "Not run here yet: `kneas-bench ablation" in text  # no ablation manifest
    # ours in the paper's layout, the paper's published tables beside
    assert "### Ours: Table 1" in text and "| Abdomen | 3M | — | 33.276 |" in text
    assert "| 5 | 20.596 | 21.767 |" in text and "| K-NeAS | 31.630 |" not in text  # Table 3 printed only when run
    assert f"{sum(1 for c in t1 if (c.scene, c.method, c.k) in psnr)} of {len(t1)} cells complete" in text
    claims = _page_lines(text, "- **")
    def verdict(scene, words):
        (line,) = [x for x in claims if f"on {Path(scene).name}:" in x and words in x]
        return line.split("**")[1]
    assert verdict("abdomen", "Abdomen: K-NeAS above NeAS") == "holds"
    assert verdict("abdomen", "best at K = 3") == "holds"
    assert verdict("jaw", "Jaw: K-NeAS below NeAS") == "does not hold"
    assert "K-NeAS 2M − NeAS 2M = +0.90 dB" in next(x for x in claims if "on jaw:" in x)
    assert verdict(knee, "K-NeAS against NeAS") == "not comparable"
    assert "| knee.pickle | 1M |" in text  # a scene file by its name in the tables, not the path it ran from
    assert not [line for line in text.splitlines() if line.startswith(("|", "- ")) and str(tmp_path) in line]
    assert verdict("chest", "5 views: K-NeAS above NeAS") == "holds"
    assert verdict("chest", "50 views: K-NeAS below NeAS") == "not comparable"
    assert "within one standard deviation" in next(x for x in claims if "50 views: K-NeAS below" in x)
    # the classical bar: ASD-POCS's best count (23.0 dB) at 5 views is above K-NeAS's 22.1, its default count's 21.0 is not;
    # at 50 views K-NeAS's 30.5 is above the oracle's 30.1
    assert verdict("chest", "5 views: K-NeAS 2M at or above the best classical") == "does not hold"
    assert "3D PSNR 22.100 vs 23.000 (ASD-POCS best of 1-40 (oracle)" in next(x for x in claims if "5 views: K-NeAS 2M at or above" in x)
    assert verdict("chest", "5 views: K-NeAS, K found at or above the best classical") == "holds"
    assert "| chest | 5 K-NeAS, K found (K = 4) |" in text
    assert "| chest | 5 ASD-POCS best of 1-40 (oracle) | — | — | — | — | 23.000 | — | 0.700 | — |" in text
    assert verdict("chest", "50 views: K-NeAS 2M at or above the best classical") == "holds"
    assert text.count("- **") == len(claims) and f"Verdicts: {sum('holds**' in x for x in claims)} holds" in text


def test_results_page_says_failed_cells_and_one_seed_ties_are_not_comparable(tmp_path):
    from kneas_method.bench import page

    out = tmp_path / "bench"
    cells = grid.ablation(["foot"], (0,), "cpu", references=())
    psnr = {"kselector": 31.0, "kselector-floater": 31.1, "k-neas": 32.0}  # kselector-shared failed
    for c in cells:
        if c.method in psnr:
            _write_metrics(out, c, _m(40.0, 0.9, psnr[c.method], 0.8), "built-in phantom foot")
        else:
            cell_dir(out, c).mkdir(parents=True)
            (cell_dir(out, c) / "cell.json").write_text(json.dumps({"status": "failed", "error": "boom"}))
    page.write_manifest(out, "ablation", cells)
    claims = _page_lines(page.render(out), "- **")
    assert len(claims) == 4
    floater = next(x for x in claims if x.startswith("- **") and "K-Selector + Floater Reg above K-Selector " in x)
    assert floater.startswith("- **not comparable**") and "rerun with --seeds 3" in floater
    shared = [x for x in claims if "Shared Body" in x]
    assert all(x.startswith("- **not comparable**") and "failed" in x for x in shared)
    full = next(x for x in claims if "K-NeAS above K-Selector + Floater Reg" in x)
    assert full.startswith("- **holds**") and "(one seed)" in full


def test_a_table_stopped_mid_cell_resumes_and_the_page_counts_every_cell(tmp_path, fake_prefix):
    import subprocess

    out, log = tmp_path / "bench", tmp_path / "calls.jsonl"
    code = ("import sys; from kneas_method.cli import bench; bench.TRAIN_PREFIX = tuple(sys.argv[1:3]); "
            "bench.main(sys.argv[3:])")
    argv = [sys.executable, "-c", code, *fake_prefix, "views", "--preset", "tiny", "--seeds", "1", "--views", "5", "10",
            "--references", "asd-pocs", "--output-dir", str(out)]
    env = {**os.environ, "FAKE_LOG": str(log), "FAKE_STOP": "chest/k-neas/2/0"}
    first = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120)
    assert first.returncode != 0 and "interrupted" in first.stderr
    stopped = [c for c in _calls(log) if c["args"][0] == "k-neas"]
    assert len(stopped) == 1 and stopped[0]["args"][stopped[0]["args"].index("--views") + 1] == "5"
    assert (out / "views.cells.json").is_file()  # the manifest is written before any cell runs
    done_before = len(_calls(log))
    env.pop("FAKE_STOP")
    second = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    again = _calls(log)[done_before:]
    assert again[0]["args"][0] == "--resume" and again[0]["args"][1].endswith("20240101-000009")
    assert [c["args"][0] for c in again[1:]].count("k-neas") == 3  # K found at 5 views, then both 10-view cells, once each
    assert sum(1 for c in _calls(log) if c["args"][0] == "neas-2m") == 2  # 5 views before the stop, 10 after; none twice
    page_run = subprocess.run([sys.executable, "-c", "from kneas_method.cli.bench import main; main()", "page", "--output-dir",
                               str(out), "--write", str(tmp_path / "page.md")], capture_output=True, text=True, timeout=120)
    assert page_run.returncode == 0, page_run.stderr
    assert "12 of 12 cells complete" in (tmp_path / "page.md").read_text()


def test_page_without_a_table_is_a_one_line_error(tmp_path, capsys):
    from kneas_method.cli import bench as cli

    (tmp_path / "empty").mkdir()
    for folder in (tmp_path / "missing", tmp_path / "empty"):
        with pytest.raises(SystemExit) as exc:
            cli.main(["page", "--output-dir", str(folder), "--write", str(tmp_path / "p.md")])
        assert exc.value.code != 0
        err = capsys.readouterr().err
        assert "run a table first" in err or "no table has run" in err
        assert "Traceback" not in err
    assert not (tmp_path / "p.md").exists()


def test_a_view_count_that_keeps_every_view_shares_the_all_views_cell(tmp_path, fake_prefix, monkeypatch):
    """Table 2's 50-view cells on a 50-view scene train what Table 1's cells train: they run once, in either
    order; the manifest records the shared folder, so the page reads it without the scene file."""
    from kneas_method.bench import page
    from kneas_method.bench.cells import own_folders_first

    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    out = tmp_path / "bench"
    views = grid.views_table(["chest"], (0,), "tiny", views=(10, 50), references=("fdk",), found_k=False)
    shared = {(c.method, c.views): c.folder for c in views if c.folder}
    assert shared == {(m, 50): grid.Cell("chest", m, k, None, 0, "tiny").id for m, k in (("neas-2m", 2), ("k-neas", 2), ("fdk", None))}
    backends.LocalBackend().run(views, out, fake_prefix)
    assert len(_calls(log)) == 6
    page.add_to_manifest(out, "views", views)
    first = grid.table1(["chest"], (0,), "tiny", ks=(2,), references=("fdk",))
    assert all(is_complete(out, c) for c in first)  # the 50-view cells' runs are Table 1's cells
    read = page.read_manifest(out, "views")
    assert [c.folder for c in read] == [c.folder for c in views]
    table = aggregate.views_table(read, aggregate.collect(out, read))
    assert [r.labels[1] for r in table.rows if not r.reference] == ["10", "50"]
    assert all(table.rows[1].entries[(m, model)] is not None for m in aggregate.METRICS for model in ("NeAS", "K-NeAS"))
    # a scene file whose views are not all asked for shares nothing; a cell that ran in its own folder keeps it
    assert not [c for c in grid.views_table(["chest"], (0,), "tiny", views=(10, 20), found_k=False) if c.folder]
    (out / "cells" / views[-1].id).mkdir(parents=True, exist_ok=True)
    kept = own_folders_first(out, views)
    assert kept[-1].folder is None and [c.folder for c in kept[:-1]] == [c.folder for c in views[:-1]]
