"""Training in blocks: the split over the seabed, the merge, and the whole job on a local Ray
(a worker killed mid-block, the block resumed from its checkpoint, one scene at the end)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, write_rendered_scene
from recgs_addon.core.blocks.merge import merge_gaussians, summarise, ViewScore
from recgs_addon.core.blocks.split import BlockPlan, plan_blocks, seabed_axes
from recgs_addon.core.errors import RecGSError
from recgs_addon.core.io.colmap import Scene
from recgs_addon.core.model.cameras import Camera
from recgs_addon.core.model.cells import EDGE, Cell
from recgs_addon.core.model.gaussians import GaussianSet


def strip_survey(n_rows=3, per_row=12, length=8.0, width=2.0, altitude=1.0, tilt=None, seed=0):
    """A Scene (in memory) of a lawnmower survey over a strip of seabed along x, looking down
    from ``altitude``, with the seabed plane tilted by ``tilt`` (a rotation) if given."""
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(0, length, 4000), rng.uniform(0, width, 4000), rng.normal(0, 0.02, 4000)]
    cams = []
    Rdown = np.diag([1.0, -1.0, -1.0])
    k = 0
    for r in range(n_rows):
        for i in range(per_row):
            c = np.array([length * (i + 0.5) / per_row, width * (r + 0.5) / n_rows, altitude])
            cams.append(Camera(f"img_{k:03d}.png", 64, 48, 40.0, 40.0, 32.0, 24.0, Rdown, -Rdown @ c))
            k += 1
    if tilt is not None:
        pts = pts @ tilt.T
        cams = [Camera(c.name, c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.R @ tilt.T, c.t) for c in cams]
    return Scene(Path("strip"), Path("strip"), Path("strip"), cams, pts.astype(np.float32),
                 np.zeros((len(pts), 3), np.uint8))


def test_cell_contains_grows_and_round_trips():
    cell = Cell((1.0, 2.0, 0.0), ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), (0.0, 1.0, -EDGE, 0.5))
    pts = np.array([[1.0, 2.0, 5.0], [1.99, 2.49, -3.0], [2.0, 2.0, 0.0], [0.99, 2.0, 0.0], [1.5, 2.5, 0.0]])
    assert cell.contains(pts).tolist() == [True, True, False, False, False]   # lower bound in, upper out
    assert cell.grown(0.1).contains(pts).tolist() == [True, True, True, True, True]
    again = Cell.from_dict(json.loads(json.dumps(cell.to_dict())))
    assert again == cell


def test_seabed_axes_follow_a_tilted_strip():
    a = np.deg2rad(20)
    tilt = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    scene = strip_survey(tilt=tilt)
    _, u, v = seabed_axes(scene.points, np.stack([c.center for c in scene.cameras]))
    assert abs(abs(u @ tilt[:, 0]) - 1) < 1e-3     # along the strip, in its tilted plane
    assert abs(np.cross(u, v) @ tilt[:, 2]) > 0.999   # the normal is the strip's


@pytest.mark.parametrize("n, grid", [(2, (2, 1)), (4, (4, 1)), (6, (6, 1))])
def test_split_covers_the_seabed_once_and_balances_the_photos(n, grid):
    scene = strip_survey()
    test = [c.name for c in scene.cameras[4::8]]
    plan = plan_blocks(scene, n, test)
    assert plan.grid == grid   # cells closest to square along a strip 4x longer than wide
    # every point of the world in exactly one cell
    probe = np.random.default_rng(1).uniform(-50, 50, (5000, 3))
    counts = sum(b.cell.contains(probe).astype(int) for b in plan.blocks)
    assert (counts == 1).all()
    # held-out photos train no block; each is scored by exactly one block
    for b in plan.blocks:
        assert not set(b.train) & set(test)
    assert sorted(sum((b.test for b in plan.blocks), [])) == sorted(test)
    # every training photo trains some block, and blocks are about as large as each other
    trained = set().union(*(b.train for b in plan.blocks))
    assert trained == {c.name for c in scene.cameras} - set(test)
    owned = [sum(1 for v in plan.owner.values() if v == b.name) for b in plan.blocks]
    assert max(owned) - min(owned) <= 3
    # a block's photos see its grown cell; a photo far from it is not among them
    for b in plan.blocks:
        u0, u1 = b.grown.bounds[:2]
        for c in scene.cameras:
            x = b.cell.plane_coords(c.center[None])[0, 0]
            if c.name in b.train:
                assert u0 - 1.5 < x < u1 + 1.5   # a footprint is ~1.6 m across
    # the plan survives its file
    assert BlockPlan.from_dict(json.loads(json.dumps(plan.to_dict()))).to_dict() == plan.to_dict()


def test_seam_views_are_those_that_see_two_cells():
    scene = strip_survey()
    held = scene.cameras[::2]
    plan = plan_blocks(scene, 2, [c.name for c in held])
    cut = plan.blocks[0].cell.bounds[1]
    assert plan.seam_views
    for c in held:
        x = plan.blocks[0].cell.plane_coords(c.center[None])[0, 0]
        # a footprint is 1.6 m across (64 px at 40 px/m, 1 m up): within 0.6 m of the cut it crosses
        if abs(x - cut) < 0.6:
            assert c.name in plan.seam_views
        elif abs(x - cut) > 1.0:
            assert c.name not in plan.seam_views


def test_too_many_blocks_is_refused_with_what_to_do():
    scene = strip_survey(n_rows=1, per_row=6)
    with pytest.raises(RecGSError, match="fewer blocks"):
        plan_blocks(scene, 6, [])
    with pytest.raises(RecGSError, match="2 or more"):
        plan_blocks(scene, 1, [])


def gaussians(means, degree=0, seed=0):
    rng = np.random.default_rng(seed)
    n = len(means)
    return GaussianSet(means, rng.normal(-3, 0.1, (n, 3)), rng.normal(size=(n, 4)), rng.normal(size=n),
                       rng.normal(size=(n, (degree + 1) ** 2, 3)))


def test_merge_keeps_each_blocks_own_cell_and_pads_sh():
    axes = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    left = Cell((0.0, 0.0, 0.0), axes, (-EDGE, 0.0, -EDGE, EDGE))
    right = Cell((0.0, 0.0, 0.0), axes, (0.0, EDGE, -EDGE, EDGE))
    rng = np.random.default_rng(0)
    a = gaussians(np.c_[rng.uniform(-2, 0.5, 300), rng.uniform(-1, 1, (300, 2))], degree=0)   # trained left + margin
    b = gaussians(np.c_[rng.uniform(-0.5, 2, 200), rng.uniform(-1, 1, (200, 2))], degree=2, seed=1)
    merged, kept = merge_gaussians([(a, left), (b, right)])
    assert kept == [int((a.means[:, 0] < 0).sum()), int((b.means[:, 0] >= 0).sum())]
    assert len(merged) == sum(kept) and merged.sh_degree == 2
    np.testing.assert_array_equal(merged.means[:kept[0]], a.means[a.means[:, 0] < 0])
    np.testing.assert_array_equal(merged.sh[:kept[0], :1], a.sh[a.means[:, 0] < 0])
    assert not merged.sh[:kept[0], 1:].any()   # degree 0's colours, unchanged at degree 2
    np.testing.assert_array_equal(merged.sh[kept[0]:], b.sh[b.means[:, 0] >= 0])


def test_summary_splits_seam_views_from_the_rest():
    s = summarise([ViewScore("a", 20.0, None, True), ViewScore("b", 30.0, None, False),
                   ViewScore("c", 28.0, None, False)])
    assert s["psnr"] == pytest.approx(26.0) and s["psnr_seam"] == 20.0 and s["psnr_inner"] == 29.0
    assert s["psnr_gt"] is None and s["seam_views"] == 1


def _events(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.is_file() else []


def blocks_job(tmp_path, n_views: int, iterations: int, *extra: str) -> tuple[list[str], Path, dict]:
    """(the command of a 2-block job on a tiny survey of ``n_views``, its OUT, its environment)."""
    pytest.importorskip("ray")
    survey = tmp_path / "survey"
    write_rendered_scene(survey, n_views=n_views, width=40, height=30, n_gauss=20 * n_views, downward=True,
                         heights=[1.2] * n_views)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "recgs_addon", "train", str(survey), "--out", str(out), "--blocks", "2",
           "--iterations", str(iterations), "--checkpoint-every", "0.3", "--eager", "--medium", "off",
           "--lamp", "off", *extra]
    return cmd, out, {**os.environ, "PYTHONPATH": str(ROOT)}


def test_blocks_on_local_ray_survive_a_killed_worker(tmp_path):
    cmd, out, env = blocks_job(tmp_path, 20, 500, "--holdout-every", "5")
    job = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    block = out / "blocks" / "block01"
    killed = None
    t0 = time.time()
    try:
        while time.time() - t0 < 300 and job.poll() is None:
            if any(e["event"] == "checkpoint" for e in _events(block / "events.jsonl")):
                assert not (block / "metrics.json").exists(), "the block ended before it could be killed"
                killed = int((block / "worker.pid").read_text())
                os.kill(killed, signal.SIGKILL)
                break
            time.sleep(0.2)
        stdout, stderr = job.communicate(timeout=420)
    finally:
        if job.poll() is None:
            job.kill()
    assert killed is not None, stderr[-2000:]
    assert job.returncode == 0, stderr[-3000:]
    events = [json.loads(x) for x in stdout.splitlines() if x.startswith("{")]
    done = events[-1]
    assert done["event"] == "done" and done["status"] == "done"
    # the killed block started twice, the second time from its checkpoint, and finished
    starts = [e for e in _events(block / "events.jsonl") if e["event"] == "start"]
    assert len(starts) == 2 and not starts[0]["resumed"] and starts[1]["resumed"] and starts[1]["iteration"] > 0
    b1 = next(b for b in done["blocks"] if b["block"] == "block01")
    assert b1["resumed"] and b1["iterations"] == 500
    # one scene: the merged PLY holds each block's own Gaussians, scored on every held-out photo
    from recgs_addon.core.io.ply import read_gaussian_ply

    merged = read_gaussian_ply(out / "point_cloud.ply")
    assert len(merged) == sum(b["kept"] for b in done["blocks"]) == done["gaussians"]
    assert done["scores"]["views"] == 4 and done["psnr_test"] > 20
    assert any(e["event"] == "progress" and len(e["blocks"]) == 2 for e in events)
    report = (out / "report.md").read_text()
    assert report.count("block0") >= 2
    # the seam-crossing held-out photos, rendered beside the photo, in the report
    assert done["seam_figures"] and all((out / f).is_file() and f in report for f in done["seam_figures"])


@pytest.mark.slow
def test_blocks_cancel_and_resume(tmp_path):
    cmd, out, env = blocks_job(tmp_path, 16, 600)
    job = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    blocks = [out / "blocks" / n for n in ("block01", "block02")]
    t0 = time.time()
    while time.time() - t0 < 300 and job.poll() is None:
        if all(any(e["event"] == "checkpoint" for e in _events(b / "events.jsonl")) for b in blocks):
            job.send_signal(signal.SIGTERM)
            break
        time.sleep(0.2)
    stdout, stderr = job.communicate(timeout=300)
    assert job.returncode == 0, stderr[-3000:]
    done = [json.loads(x) for x in stdout.splitlines() if x.startswith("{")][-1]
    assert done["event"] == "done" and done["status"] == "cancelled", done
    for b in blocks:   # each stopped after a checkpoint, not done
        assert (b / "checkpoint.pt").is_file() and not (b / "metrics.json").is_file()
        assert [e for e in _events(b / "events.jsonl") if e["event"] == "done"][-1]["status"] == "cancelled"
    assert (out / "point_cloud.ply").is_file()   # what the blocks had, merged

    r = subprocess.run(cmd + ["--resume"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    done = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")][-1]
    assert done["status"] == "done"
    for b in done["blocks"]:
        assert b["starts"] == 2 and b["resumed"] and b["iterations"] == 600


def test_blocks_without_ray_say_how_to_get_it(tmp_path, monkeypatch, capsys):
    from recgs_addon.cli import build_parser, main

    monkeypatch.setitem(sys.modules, "ray", None)   # import ray fails as where it is not installed
    args = ["train", str(tmp_path), "--out", str(tmp_path / "out"), "--blocks", "2"]
    build_parser().parse_args(args)
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "not installed" in err and "pip install 'ray" in err and "setup.sh --ray" in err
    assert not (tmp_path / "out").exists()   # nothing written


def test_a_split_says_what_it_costs_in_duplicated_photos_and_a_wasteful_one_is_refused():
    from recgs_addon.core.blocks.split import MAX_DUPLICATION, check_split, fewest_duplicating

    strip = strip_survey()                                   # a strip 4 footprints long: blocks pay
    plan = plan_blocks(strip, 2, [])
    counted = sum(len(b.train) for b in plan.blocks) / len({n for b in plan.blocks for n in b.train})
    assert plan.duplication == pytest.approx(counted) and 1.0 <= plan.duplication < 1.5
    assert any("trains in" in line for line in plan.lines())
    check_split(strip, plan, [], cluster=False)              # accepted
    small = strip_survey(length=2.0, width=2.0)              # a seabed one or two footprints wide
    four = plan_blocks(small, 4, [])
    assert four.duplication > MAX_DUPLICATION and "small for this many blocks" in four.cost_line()
    with pytest.raises(RecGSError) as err:
        check_split(small, four, [], cluster=False)
    fits = fewest_duplicating(small, [], 3)
    assert 1 <= fits < 4 and (fits == 1 or plan_blocks(small, fits, []).duplication <= MAX_DUPLICATION)
    assert "4 blocks would train each photo in" in str(err.value)
    assert (f"at most {fits} blocks" if fits > 1 else "one job") in str(err.value)
    check_split(small, four, [], cluster=True)               # more machines: said, not refused


def test_blocks_auto_is_one_job_where_it_fits_and_the_fewest_blocks_that_fit_otherwise():
    from recgs_addon.core.blocks.split import auto_blocks

    strip = strip_survey()
    n, why = auto_blocks(strip, [], one_job_bytes=2 * 2 ** 30, available=8 * 2 ** 30)
    assert n == 1 and "one job" in why
    assert auto_blocks(strip, [], 2 * 2 ** 30, None)[0] == 1   # memory unknown: one job
    n, why = auto_blocks(strip, [], one_job_bytes=10 * 2 ** 30, available=4 * 2 ** 30)
    plan = plan_blocks(strip, n, [])
    assert n >= 3 and 10 * plan.duplication / n <= 4        # each block's share fits ...
    smaller = plan_blocks(strip, n - 1, [])
    assert 10 * smaller.duplication / (n - 1) > 4             # ... and one block fewer would not
    assert f"{n} blocks" in why
    with pytest.raises(RecGSError, match="no split"):
        auto_blocks(strip, [], one_job_bytes=10 ** 15, available=2 ** 30, most=6)


def test_the_blocks_option_takes_a_count_or_auto():
    import argparse

    from recgs_addon.core.options.train import AUTO_BLOCKS, blocks_count

    assert blocks_count("auto") == AUTO_BLOCKS and blocks_count("AUTO") == AUTO_BLOCKS
    assert blocks_count("4") == 4 and blocks_count(0) == 0
    for bad in ("-2", "four"):
        with pytest.raises(argparse.ArgumentTypeError):
            blocks_count(bad)


def test_train_with_blocks_auto_trains_one_job_where_it_fits(tmp_path):
    survey = tmp_path / "survey"
    write_rendered_scene(survey, n_views=8, width=40, height=30, n_gauss=160, downward=True, heights=[1.2] * 8)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "recgs_addon", "train", str(survey), "--out", str(out), "--blocks",
                        "auto", "--iterations", "5", "--eager", "--medium", "off", "--lamp", "off"],
                       cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "--blocks auto: one job" in r.stderr
    assert (out / "metrics.json").is_file() and not (out / "blocks").exists()


def test_each_block_gets_its_round_of_the_time_left_after_the_split_and_before_the_merge():
    from recgs_addon.commands.blocks import MERGE_SHARE, block_minutes

    # 4 blocks on 2 workers: two rounds of what is left
    assert block_minutes(10.0, 30.0, 4, 2) == pytest.approx((600 * (1 - MERGE_SHARE) - 30) / 2 / 60)
    # 3 blocks on 2 workers are two rounds too, not one and a half
    assert block_minutes(10.0, 0.0, 3, 2) == pytest.approx(600 * (1 - MERGE_SHARE) / 2 / 60)
    for n, w in ((1, 1), (5, 2), (8, 3), (6, 6)):
        rounds = -(-n // w)
        assert rounds * block_minutes(5.0, 12.0, n, w) * 60 + 12.0 <= 300 * (1 - MERGE_SHARE) + 1e-6
    assert block_minutes(1.0, 500.0, 2, 2) > 0          # spent more than the limit: a token time, not 0


def test_a_split_made_from_the_survey_geometry_made_once_is_the_same_split():
    from recgs_addon.core.blocks.split import split_geometry

    strip = strip_survey()
    geometry = split_geometry(strip)
    for n in (2, 3, 4):
        assert plan_blocks(strip, n, ["img_004.png"], geometry=geometry).to_dict() == \
            plan_blocks(strip, n, ["img_004.png"]).to_dict()
