"""The pass estimator (core/caustics/passes.py) on an analytic seabed: a textured plane seen
from above by a lawnmower of frames, under a network of bright lines that moves between them."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from recgs_addon.core.caustics import geometry as G
from recgs_addon.core.caustics import passes as P
from recgs_addon.core.caustics.estimators import LIGHT_FLOOR
from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
from recgs_addon.core.train.losses import psnr

W, H, F = 96, 72, 120.0   # image size and focal length (pixels): 2 cm a pixel on the seabed
ALTITUDE = 2.5
_rng = np.random.default_rng(7)
SAND = [(r * math.cos(th), r * math.sin(th), ph) for r, th, ph in
        zip(_rng.uniform(2 * math.pi / 0.2, 2 * math.pi / 0.1, 8), _rng.uniform(0, math.pi, 8), _rng.uniform(0, 6.3, 8))]


def albedo(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(..., 3) linear albedo of the seabed at world (x, y): broad patches and fine texture."""
    a = 0.18 + 0.08 * torch.sin(1.7 * x + 0.3) * torch.cos(1.3 * y)
    for k, (kx, ky, ph) in enumerate(SAND):   # sand: fine texture of periods 10-20 cm (5-10 px)
        a = a + 0.03 * torch.sin(kx * x + ky * y + ph)
    return torch.stack([a * 0.8, a, a * 1.1], -1).clamp_min(0.02)


def light(x: torch.Tensor, y: torch.Tensor, t: float, strength: float) -> torch.Tensor:
    """Caustic gain (mean about 1): thin bright lines over a dimmer floor, moving with ``t``."""
    if strength == 0:
        return torch.ones_like(x)
    s1 = torch.sin(5.0 * x + 2.1 * t + 0.7 * torch.sin(3.0 * y + t))
    s2 = torch.sin(4.3 * y - 1.7 * t + 0.9 * torch.sin(2.5 * x - 0.6 * t))
    lines = torch.exp(-(s1 / 0.25) ** 2) + torch.exp(-(s2 / 0.25) ** 2)
    g = 0.25 + lines
    return 1.0 + strength * (g / 0.62 - 1.0)


def camera(cx: float, cy: float):
    """(viewmat (4, 4), K (3, 3)) of a camera at (cx, cy, ALTITUDE) looking straight down."""
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    C = torch.tensor([cx, cy, ALTITUDE])
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ C
    K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
    return vm, K


def frame(cx, cy, t, strength):
    """(photo sRGB (H, W, 3), ground truth sRGB, depth (H, W), viewmat, K) of one frame."""
    vm, K = camera(cx, cy)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    x = cx + (u - W / 2) / F * ALTITUDE
    y = cy - (v - H / 2) / F * ALTITUDE
    a = albedo(x, y)
    g = light(x, y, t, strength).unsqueeze(-1)
    photo = linear_to_srgb((a * g).clamp(0, 1))
    return photo, linear_to_srgb(a), torch.full((H, W), ALTITUDE), vm, K


def survey(strength=0.9, rows=3, per_row=10, step=0.15, row_gap=0.6, dt=0.33, light_speed=1.0):
    """Frames along a lawnmower (``rows`` rows of ``per_row`` frames, ``dt`` s apart), the light
    moving ``light_speed`` times as fast as ``light`` says."""
    views, gts = [], []
    t = 0.0
    for r in range(rows):
        xs = [k * step for k in range(per_row)]
        if r % 2:
            xs = xs[::-1]
        for x in xs:
            photo, gt, depth, vm, K = frame(x, r * row_gap, t * light_speed, strength)
            views.append(G.PassView(photo, depth, torch.ones(H, W, dtype=torch.bool), vm, K, t))
            gts.append(gt)
            t += dt
        t += 6.0   # the turn at the end of a row
    return views, gts


def test_choose_passes_groups_by_time_and_respects_sources_and_budget():
    views, _ = survey(rows=2, per_row=8)
    ov = G.overlap_matrix(views)
    s = P.PassSettings(pass_seconds=1.0, per_pass=2, max_frames=6)
    groups = P.choose_passes(3, views, ov, s)
    assert groups[0][0] == 3
    assert sum(len(g) for g in groups[1:]) + len(groups[0]) - 1 <= 6
    for g in groups[1:]:
        ts = [views[j].time for j in g]
        assert max(ts) - min(ts) < 1.0 and all(abs(t - views[3].time) >= 1.0 for t in ts)
    for j in groups[0][1:]:
        assert abs(views[j].time - views[3].time) < 1.0
    only = list(range(8, 16))   # the other row only
    groups = P.choose_passes(3, views, ov, s, sources=only)
    assert all(j in only for g in groups[1:] for j in g) and groups[0] == [3]


@pytest.mark.parametrize("statistic", ["field", "floor"])
def test_targets_take_the_light_out_and_keep_the_mean_light(statistic):
    views, gts = survey()
    targets, info = P.pass_targets(views, P.PassSettings(pass_seconds=0.5, statistic=statistic))
    mid = [k for k in range(len(views)) if info["share"][k] > 0.5]
    assert len(mid) > len(views) // 2
    photos = np.mean([psnr(views[k].photo, gts[k]) for k in mid])
    got = np.mean([psnr(targets[k].clamp(0, 1), gts[k]) for k in mid])
    assert got > photos + 6.0, (photos, got)
    # the floor of the light is brought back to the mean light the photos hold (linear light)
    lin = [srgb_to_linear(targets[k].clamp(0, 1)).sum((0, 1)) for k in mid]
    ref = [srgb_to_linear(views[k].photo).sum((0, 1)) for k in mid]
    ratio = torch.stack(lin).sum(0) / torch.stack(ref).sum(0)
    assert ((ratio - 1).abs() < 0.03).all(), ratio


def test_too_few_passes_keep_the_fallback():
    views, _ = survey(rows=1, per_row=3, step=0.2)
    fallback = [torch.full_like(v.photo, 0.5) for v in views]
    targets, info = P.pass_targets(views, P.PassSettings(pass_seconds=10.0, min_passes=2), fallback)
    for t in targets:   # all frames within one pass: nothing but the fallback
        assert torch.equal(t, torch.full_like(t, 0.5))
    assert info["share"] == [0.0] * 3


def test_light_statistics_measure_the_light_and_its_time():
    views, _ = survey(strength=0.0, rows=2, per_row=10)
    still = P.light_statistics(views, G.overlap_matrix(views))
    assert still["light_std"] < LIGHT_FLOOR / 2   # resampled texture only
    views, _ = survey(strength=0.9, rows=2, per_row=10)
    lit = P.light_statistics(views, G.overlap_matrix(views))
    assert lit["light_std"] > 0.15
    assert lit["correlation_s"] is not None and lit["correlation_s"] <= 1.0
    slow, _ = survey(strength=0.9, rows=2, per_row=10, light_speed=0.25)   # the light moves 4x slower
    assert P.light_statistics(slow, G.overlap_matrix(slow))["correlation_s"] >= 2 * lit["correlation_s"]


def test_points_depth_interpolates_a_slanted_plane():
    vm, K = camera(0.0, 0.0)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (600, 2))
    z = 0.1 * xy[:, 0]                     # seabed sloping along x
    pts = torch.tensor(np.c_[xy, z], dtype=torch.float32)
    d = G.points_depth(vm, K, H, W, pts)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    # exact depth of the plane z = 0.1 x through each pixel's ray
    rx = (u - W / 2) / F
    true = ALTITUDE / (1 + 0.1 * rx)
    ok = torch.isfinite(d)
    assert ok.float().mean() > 0.95
    assert ((d[ok] - true[ok]).abs() / true[ok]).median() < 0.005


def test_refine_depth_aligns_texture():
    views, _ = survey(strength=0.9, rows=2, per_row=8)
    ov = G.overlap_matrix(views)
    i = 4
    true = views[i].surface.clone()
    views[i].surface = true * 1.012          # a prior 1.2 % too far
    nbrs = G.sweep_neighbours(i, views, ov)
    assert nbrs and i not in nbrs
    refined = G.refine_depth(i, views, nbrs)
    before = ((views[i].surface - true).abs() / true).median()
    after = ((refined - true).abs() / true).median()
    assert after < 0.6 * before, (before, after)


def test_survey_geometry_prefers_points_to_a_short_model_depth():
    views, _ = survey(strength=0.9, rows=2, per_row=8)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1, 3, (3000, 2))
    pts = torch.tensor(np.c_[xy, np.zeros(len(xy))], dtype=torch.float32)
    for v in views:   # a model whose Gaussians float 4 % in front of the seabed
        v.surface = v.surface * 0.96
    G.survey_geometry(views, pts)
    err = torch.stack([((v.surface - ALTITUDE).abs() / ALTITUDE).median() for v in views])
    assert err.max() < 0.005, err


BLOCK = (0.35, 0.85, 0.05, 0.45)   # a block standing on the seabed: x0, x1, y0, y1 (m) ...
BLOCK_H = 0.35                     # ... and its height, 14 % of the camera's range


def relief_frame(cx: float, cy: float):
    """(photo sRGB, depth, viewmat, K) of a frame above a seabed with :data:`BLOCK` on it
    (rays marched to the first surface: the block's top and sides hide the sand behind)."""
    vm, K = camera(cx, cy)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    dx, dy = (u - W / 2) / F, -(v - H / 2) / F
    ts = torch.linspace(ALTITUDE - BLOCK_H - 0.01, ALTITUDE, 800).view(-1, 1, 1)
    x, y, z = cx + ts * dx, cy + ts * dy, ALTITUDE - ts
    inb = (x >= BLOCK[0]) & (x <= BLOCK[1]) & (y >= BLOCK[2]) & (y <= BLOCK[3])
    first = torch.argmax((z <= BLOCK_H * inb).int(), 0)
    t = ts.flatten()[first]
    hz = ALTITUDE - t
    photo = linear_to_srgb(albedo(cx + t * dx + 1.3 * hz, cy + t * dy - 0.7 * hz))
    return photo, t, vm, K


def test_relief_layers_keep_a_block_off_the_sand_around_it():
    """The points' blur spreads a block's top into the sand around it and the sand into its
    top; the near and far layers, swept, put most of those pixels back on their surface."""
    frames = [relief_frame(k * 0.15, r * 0.6) for r in range(2) for k in range(8)]
    rng = np.random.default_rng(3)
    top = np.c_[rng.uniform(BLOCK[0], BLOCK[1], 12), rng.uniform(BLOCK[2], BLOCK[3], 12), np.full(12, BLOCK_H)]
    sand = np.c_[rng.uniform(-1.2, 2.3, 546), rng.uniform(-0.8, 1.8, 546)]
    under = (sand[:, 0] >= BLOCK[0]) & (sand[:, 0] <= BLOCK[1]) & (sand[:, 1] >= BLOCK[2]) & (sand[:, 1] <= BLOCK[3])
    sand = sand[~under]
    pts = torch.tensor(np.r_[top, np.c_[sand, np.zeros(len(sand))]], dtype=torch.float32)
    share = {}
    for relief in (False, True):
        views = [G.PassView(ph, torch.full((H, W), float("nan")), torch.zeros(H, W, dtype=torch.bool), vm, K, 0.33 * k)
                 for k, (ph, _, vm, K) in enumerate(frames)]
        if relief:
            G.survey_geometry(views, pts)
        else:
            brought = G.prior_geometry(views, pts)
            G.refine_geometry(views, G.overlap_matrix(views), brought)   # no points: no relief layers
        err = torch.cat([((v.surface - d).abs() / d)[v.covered] for v, (_, d, _, _) in zip(views, frames)])
        assert float(err.median()) < 0.002
        share[relief] = float((err > 0.03).float().mean())
    assert share[False] > 0.03, share              # the blur does miss the block's edges ...
    assert share[True] < 0.6 * share[False], share  # ... and the layers find most of them


def test_sweep_scores_in_a_window_match_the_whole_frame():
    """Scoring only a window of a frame (where its relief is) gives the whole frame's scores
    there, but for the correlation windows cut by its edge (to the running sums' rounding)."""
    views, _ = survey(strength=0.9, rows=2, per_row=8)
    i = 4
    nbrs = G.sweep_neighbours(i, views, G.overlap_matrix(views))
    greys = [G.log_grey(v.photo) for v in views]
    depths = [views[i].surface * (1 + d) for d in (-0.01, 0.0, 0.01)]
    full = G._sweep_scores(i, views, nbrs, depths, 2, greys)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[20:40, 30:70] = True
    win = G._bounds(mask, 4)
    assert (win[0].start, win[0].stop, win[1].start, win[1].stop) == (16, 44, 26, 74)
    part = G._sweep_scores(i, views, nbrs, [d[win] for d in depths], 2, greys, win)
    assert torch.allclose(part[:, 2:-2, 2:-2], full[:, win[0], win[1]][:, 2:-2, 2:-2], atol=1e-3)


def test_sweep_scores_are_the_mean_correlation_with_each_neighbour_that_sees_the_point(monkeypatch):
    """The batched scoring (every depth, every neighbour, three box filters in one call, split
    into batches when large) equals scoring one depth and one neighbour at a time with
    ``zncc``, where the warped point lands inside that neighbour."""
    views, _ = survey(strength=0.9, rows=2, per_row=8)
    i = 4
    nbrs = G.sweep_neighbours(i, views, G.overlap_matrix(views))
    greys = [G.log_grey(v.photo) for v in views]
    depths = [views[i].surface * (1 + d) for d in (-0.02, -0.005, 0.0, 0.01, 0.03)]
    pairs = [G._pair_rays(views[i], views[j]) for j in nbrs]
    want = []
    for z in depths:
        num, cnt = torch.zeros(H, W), torch.zeros(H, W)
        for (rays, e), j in zip(pairs, nbrs):
            g, ok = G._pair_grid(rays, e, z.unsqueeze(0), views[j])
            b = torch.nn.functional.grid_sample(greys[j][None, None], g, mode="bilinear", align_corners=False)[0]
            num += G.zncc(greys[i].unsqueeze(0), b, 2)[0] * ok[0]
            cnt += ok[0]
        want.append(num / cnt.clamp_min(1))
    want = torch.stack(want)
    got = G._sweep_scores(i, views, nbrs, depths, 2, greys)
    assert got.shape == want.shape and (want.abs() > 0.3).float().mean() > 0.5
    assert torch.allclose(got, want, atol=1e-5), (got - want).abs().max()
    monkeypatch.setattr(G, "SWEEP_BATCH", 1)           # one depth a batch
    assert torch.allclose(G._sweep_scores(i, views, nbrs, depths, 2, greys), got, atol=1e-6)


def test_pixels_without_a_surface_take_no_part_in_the_calibration():
    """Where no frame knows the surface (no points, no model), the photo's light cannot be
    compared with anything: those pixels neither calibrate the floor nor get an estimate."""
    views, _ = survey(rows=2, per_row=8)
    for v in views:
        v.covered = v.covered.clone()
        v.covered[:, :30] = False
    est, wts, info = P.pass_estimates(views, P.PassSettings(pass_seconds=0.5))
    assert all(torch.isfinite(e).all() for e in est)
    assert all((w[:, :30] == 0).all() for w in wts)
    # one frame: the floor is the photo itself (gain 1); more: the floor is darker than the mean
    assert all(0.999 < float(g.min()) and float(g.max()) < 3.0 for g in info["gains"].values())


def test_gather_through_water_puts_every_frame_at_the_frames_own_range():
    """Two frames 1.5 m and 3.5 m above the seabed, through coastal water (no caustics): taken
    as they are, the far frame's colours differ from the near one's by the water; gathered with
    the water's coefficients, each sample is the direct light at the near frame's range, the
    near frame's own veil apart."""
    water = {"attenuation": [0.5, 0.22, 0.34], "backscatter": [0.3, 0.34, 0.3], "veil": [0.012, 0.085, 0.065]}
    att, back, veil = (torch.tensor(water[k]) for k in ("attenuation", "backscatter", "veil"))
    views = []
    for cx, alt in ((0.0, 1.5), (0.05, 3.5)):
        R = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        vm = torch.eye(4)
        vm[:3, :3], vm[:3, 3] = R, -R @ torch.tensor([cx, 0.0, alt])
        K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
        v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
        x, y = cx + (u - W / 2) / F * alt, -(v - H / 2) / F * alt
        r = alt * torch.sqrt(1 + ((u - W / 2) / F) ** 2 + ((v - H / 2) / F) ** 2)
        seen = albedo(x, y) * torch.exp(-att * r.unsqueeze(-1)) + veil * (1 - torch.exp(-back * r.unsqueeze(-1)))
        views.append(G.PassView(linear_to_srgb(seen), torch.full((H, W), alt), torch.ones(H, W, dtype=torch.bool), vm, K))
    plain, ok, _, none = P.gather(0, views, [[0], [1]])
    wet, ok2, _, veil0 = P.gather(0, views, [[0], [1]], water=water)
    assert none is None and torch.equal(ok, ok2)
    both = ok[0] & ok[1]
    assert both.float().mean() > 0.2
    near, far = wet[0][both], wet[1][both]
    # what is left is the far frame's coarser sampling of the sand's texture: no bias
    assert (far - near).abs().mean() < 0.2 * (plain[1][both] - plain[0][both]).abs().mean()
    assert (far - near).mean(0).abs().max() < 1e-3 < (plain[1][both] - plain[0][both]).mean(0).abs().max()
    assert torch.allclose(wet[0] + veil0, plain[0], atol=1e-6)   # the frame itself: its veil apart


def test_a_warp_takes_nothing_from_beyond_the_other_frames_edge():
    """Where frame j's image ends, a bilinear sample would mix its edge pixels with the padding
    around them: a dark seam along j's edge in everything gathered from it. Valid samples lie
    half a pixel or more inside j, and carry j's own levels."""
    flat = torch.full((H, W, 3), 0.5)
    vi = G.PassView(flat, torch.full((H, W), ALTITUDE), torch.ones(H, W, dtype=torch.bool), *camera(0.0, 0.0))
    vj = G.PassView(flat, torch.full((H, W), ALTITUDE), torch.ones(H, W, dtype=torch.bool), *camera(0.3 * 2.5 * W / F / W * 10.3, 0.0))
    seen, ok = G.warp(vi, vj)
    assert 0 < int(ok.sum()) < H * W
    assert torch.allclose(seen[ok], torch.tensor(0.5), atol=1e-6), float((seen[ok] - 0.5).abs().max())


def test_frames_are_evened_by_the_light_fixed_to_the_camera_before_they_are_compared():
    """A vignetted survey: each frame's photo divided by the camera's light (the trainer's lamp)
    before the passes compare frames, so a frame's dark edge is not taken for the floor of the
    light; the estimates are lit again as their own frame was."""
    from types import SimpleNamespace

    from recgs_addon.core.caustics.estimators import Estimates, _relit
    from recgs_addon.core.model.lamp import TERMS, Lamp
    from recgs_addon.core.model.medium import ray_lengths

    views, gts = survey(strength=0.0, rows=1, per_row=4)
    lamp = Lamp(ALTITUDE, [0.0, 0.0, -0.8, 0.0, -0.8] + [0.0] * (TERMS - 5))
    cam = SimpleNamespace(width=W, height=H, cx=W / 2, cy=H / 2, fx=F, fy=F)
    rays = ray_lengths(W, H, F, F, W / 2, H / 2)
    even = [v.photo.clone() for v in views]
    for v in views:   # the photos as the lamp lit them
        with torch.no_grad():
            g = lamp.gain(W, H, W / 2, H / 2, v.surface * rays).unsqueeze(-1)
        v.photo = linear_to_srgb(srgb_to_linear(v.photo) * g).clamp(0, 1)
    lit = [v.photo.clone() for v in views]
    def estimates(trainer):   # the Estimates methods the evening uses, on a stand-in run
        est = SimpleNamespace(trainer=trainer, data=SimpleNamespace(camera=lambda i, level=1: cam))
        est._camera_light = lambda: Estimates._camera_light(est)
        est._even_photos = lambda vs, cams: Estimates._even_photos(est, vs, cams)
        return est
    est = estimates(SimpleNamespace(lamp=lamp, light=None, device="cpu", ray_len=lambda c: rays))
    gains = Estimates._even_the_light(est, views, list(range(len(views))))
    for k, v in enumerate(views):
        assert torch.allclose(v.photo, even[k], atol=2e-3)            # evened: the seabed alone
        assert torch.allclose(_relit(v.photo, gains, k), lit[k], atol=2e-3)
    assert Estimates._even_the_light(estimates(SimpleNamespace(lamp=None, light=None)), views, []) is None


def _disc(radius: float = 12.0, level: float = 0.7) -> torch.Tensor:
    """(H, W) log light: a bright disc over the floor (0)."""
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    return level * (((u - W / 2) ** 2 + (v - H / 2) ** 2) < radius ** 2).float()


def test_a_frames_light_is_modelled_through_the_colours_texture_error():
    """The light of a frame against a colour estimate that is wrong by fine texture: the light
    comes back (the disc, its contrast within what total variation takes off its rim) and the
    texture error does not."""
    rng = torch.Generator().manual_seed(0)
    colour = 0.05 + 0.3 * torch.rand(H, W, 1, generator=rng).expand(H, W, 3)
    true = _disc()
    photo = colour * torch.exp(true).unsqueeze(-1)
    error = 0.1 * torch.randn(H, W, generator=rng)                 # the estimate's texture error (log units)
    wrong = colour * torch.exp(error).unsqueeze(-1)
    light = P.frame_light(photo, wrong, torch.ones(H, W, dtype=torch.bool), P.PassSettings())
    assert (light - true).abs().mean() < 0.35 * error.abs().mean(), float((light - true).abs().mean())
    inside = true > 0
    assert abs(float(light[inside].mean()) - 0.7) < 0.08


def test_the_colour_is_the_photo_under_its_light_and_the_floor_under_a_bright_line():
    rng = torch.Generator().manual_seed(1)
    colour = 0.05 + 0.5 * torch.rand(H, W, 3, generator=rng)
    floor = 0.9 * colour                                      # what the passes' floor gave
    light = _disc(16.0, 3.0)                                  # a line 20 times the floor's light
    own = colour * torch.exp(light).unsqueeze(-1)
    got = P.field_colour(own, floor, light, torch.ones(H, W, dtype=torch.bool), P.PassSettings())
    dim, bright = light == 0, light > 0
    assert torch.allclose(got[dim], colour[dim], rtol=0.01)   # the photo, where its light is known
    assert torch.allclose(got[bright], floor[bright], rtol=0.01)   # the floor, under the line


def test_frames_that_saw_the_same_light_count_as_one_look():
    valid = torch.ones(3, 2, 2, dtype=torch.bool)
    assert torch.allclose(P.effective_looks(valid, [0.0, 0.0, 100.0], 1.0), torch.full((2, 2), 2.0))
    assert torch.allclose(P.effective_looks(valid, [0.0, 10.0, 20.0], 1.0), torch.full((2, 2), 3.0), atol=1e-3)
    assert torch.allclose(P.effective_looks(valid, [0.0, None, 0.0], 1.0), torch.full((2, 2), 3.0))   # no times
    valid[1, 0, 0] = False                                    # a pixel the same-instant frame missed
    assert P.effective_looks(valid, [0.0, 0.0, 100.0], 1.0)[0, 0] == pytest.approx(2.0)


def test_the_lights_decorrelation_time_is_fitted_from_its_shared_variance():
    shared = {lag: math.exp(-lag / 0.8) for lag in (0.33, 0.66, 0.99)}
    assert P.decorrelation_time(shared, 0.33) == pytest.approx(0.8, abs=1e-3)
    assert P.decorrelation_time({0.33: -0.1}, 0.33) == pytest.approx(0.033)   # gone within a frame


def test_ambiguous_depth_two_peaks_on_texture_or_a_grazing_view():
    """The passes abstain where the sweep finds two separate peaks as good (repetitive texture
    matches at several depths) on a textured window, or the surface is seen at a grazing angle;
    one clear peak, or no texture, is trusted."""
    d, h, w = 7, 10, 12
    one = torch.tensor([0.1, 0.3, 0.6, 0.9, 0.6, 0.3, 0.1]).view(d, 1, 1).expand(d, h, w)
    two = torch.tensor([0.2, 0.88, 0.5, 0.3, 0.5, 0.9, 0.2]).view(d, 1, 1).expand(d, h, w)
    textured = torch.rand(h, w, generator=torch.Generator().manual_seed(0))
    flat = torch.full((h, w), 0.5)
    assert bool(G.ambiguity(two, textured, 2).all())
    assert not bool(G.ambiguity(one, textured, 2).any())
    assert not bool(G.ambiguity(two, flat, 2).any())
    # a plane seen head-on, and tilted 80 degrees away from the view
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 8], [0, 0, 1]])
    v = G.PassView(torch.zeros(16, 20, 3), torch.full((16, 20), 2.0), torch.ones(16, 20, dtype=torch.bool),
                   torch.eye(4), K)
    assert not bool(G.grazing(v, torch.full((16, 20), 2.0)).any())
    u = (torch.arange(20, dtype=torch.float32) + 0.5 - 10) / 20
    slope = math.tan(math.radians(80))
    tilted = (2.0 / (1 - slope * u)).clamp(0.1, 100).expand(16, 20)   # z = 2 + slope * x
    assert bool(G.grazing(v, tilted)[:, 10:12].all())


def video(strength=0.9, rows=2, per_row=6, step=0.3, row_gap=0.6, dt=0.4, between=3):
    """A lawnmower filmed as a video: keyframes ``dt`` s apart, ``step`` m apart along each row,
    and ``between`` look frames between two keyframes of a row (on the line between them, at
    their own instants). Returns (keyframes, their truths, looks)."""
    keys, gts, looks = [], [], []
    t = 0.0
    for r in range(rows):
        xs = [k * step for k in range(per_row)]
        if r % 2:
            xs = xs[::-1]
        for k, x in enumerate(xs):
            photo, gt, depth, vm, K = frame(x, r * row_gap, t, strength)
            keys.append(G.PassView(photo, depth, torch.ones(H, W, dtype=torch.bool), vm, K, t))
            gts.append(gt)
            if k + 1 < per_row:
                for m in range(1, between + 1):
                    s = m / (between + 1)
                    lx = x + s * (xs[k + 1] - x)
                    photo, _, depth, vm, K = frame(lx, r * row_gap, t + s * dt, strength)
                    looks.append(G.PassView(photo, depth, torch.ones(H, W, dtype=torch.bool), vm, K, t + s * dt))
            t += dt
        t += 6.0
    return keys, gts, looks


def test_look_frames_bring_more_looks_and_closer_targets():
    """A video's frames between the keyframes are further looks at the light: gathered from,
    they raise each keyframe's independent looks and bring its target closer to the truth; the
    keyframes-only count is the one the keyframes give alone."""
    keys, gts, looks = video()
    n, m = len(keys), len(looks)
    ids = list(range(n))
    base = P.PassSettings(pass_seconds=0.4, light_seconds=0.1)
    alone, info0 = P.pass_targets(keys, base, ids=ids)
    frames = keys + looks
    wide = np.zeros((n + m, n + m))
    wide[:n, :n] = G.overlap_matrix(keys)
    wide[:n, n:] = G.overlap_block(keys, looks)
    s = P.with_looks(base, [v.time for v in frames])
    assert s.pass_seconds == pytest.approx(0.1) and s.max_frames == P.LOOK_MAX_FRAMES
    both, info = P.pass_targets(frames, s, ids=ids, overlap=wide, sources=list(range(n + m)),
                                keyframes=set(ids))
    assert np.median(info["looks"]) > 1.5 * np.median(info0["looks"])
    assert np.median(info["looks_keyframes"]) <= np.median(info["looks"])
    mid = [k for k in ids if info0["share"][k] > 0.5]
    got0 = np.mean([psnr(alone[k].clamp(0, 1), gts[k]) for k in mid])
    got = np.mean([psnr(both[k].clamp(0, 1), gts[k]) for k in mid])
    assert got > got0 + 0.5, (got0, got)


def test_overlap_block_is_the_overlap_matrix_between_two_sets():
    keys, _, looks = video(rows=1, per_row=3, between=1)
    frames = keys + looks
    full = G.overlap_matrix(frames)
    block = G.overlap_block(keys, looks)
    assert np.allclose(block, full[:len(keys), len(keys):])


def test_a_frame_placed_off_lines_up_worse_than_one_placed_right():
    """The look frames' check: a frame warped into its keyframe through the keyframe's depth
    lines up on the texture where its pose is right, whatever the light did between them, and
    loses it when the pose is a few pixels off."""
    key = G.PassView(*_frame_view(0.0, 0.0, 0.0))
    right = G.PassView(*_frame_view(0.1, 0.0, 0.4))       # moved 10 cm, the light moved on
    photo, depth, covered, vm, K, t = _frame_view(0.1, 0.0, 0.4)
    off = vm.clone()
    off[0, 3] += 0.06   # its pose 6 cm (3 pixels) off
    wrong = G.PassView(photo, depth, covered, off, K, t)
    good, bad = G.alignment(key, right), G.alignment(key, wrong)
    assert good > 0.5 and bad < 0.5 * good, (good, bad)


def _frame_view(x: float, y: float, t: float):
    photo, _, depth, vm, K = frame(x, y, t, 0.9)
    return photo, depth, torch.ones(H, W, dtype=torch.bool), vm, K, t


def test_with_look_frames_the_cap_drops_frames_of_a_pass_not_passes():
    keys, _, looks = video(rows=2, per_row=6, between=3)
    frames = keys + looks
    n = len(keys)
    wide = np.zeros((len(frames), len(frames)))
    wide[:n, :n] = G.overlap_matrix(keys)
    wide[:n, n:] = G.overlap_block(keys, looks)
    s = P.with_looks(P.PassSettings(pass_seconds=0.4, light_seconds=0.1), [v.time for v in frames])
    tight = P.choose_passes(2, frames, wide, replace(s, max_frames=6))
    loose = P.choose_passes(2, frames, wide, replace(s, max_frames=100))
    assert sum(map(len, tight)) - 1 <= 6
    own = len(tight[0]) - 1   # the frame's own pass first, as without the cap
    assert len(loose) > len(tight) == 1 + 6 - own   # then a pass for each frame the cap leaves
    assert all(len(g) == 1 for g in tight[1:])
