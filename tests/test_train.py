"""Trainer: density ops, determinism, exact resume, the job runner, bad inputs."""
import copy
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from conftest import ROOT, write_rendered_scene
from recgs_addon.core.train import density
from recgs_addon.core.errors import RecGSError
from recgs_addon.core.render.rowgrads import RowGrads
from recgs_addon.core.train.config import preset
from recgs_addon.core.train.data import holdout_split
from recgs_addon.core.train.trainer import make_trainer


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("train") / "scene"
    write_rendered_scene(root, n_views=8, width=40, height=30, n_gauss=200)
    return root


def tiny_cfg(**kw):
    base = dict(iterations=120, eval_every=40, log_every=40, holdout_every=4, compiled=False,
                densify_from=40, densify_every=40, densify_until=100, pyramid=((30, 2),))
    base.update(kw)
    return preset("default", **base)


def test_holdout_split_every_nth_from_half_a_period_in():
    names = [f"{i:02d}.png" for i in range(17)][::-1]
    train, test = holdout_split(names, 8)
    assert sorted(names[i] for i in test) == ["04.png", "12.png"]     # not the first or the last shot
    assert len(train) == 15 and not set(train) & set(test)
    assert holdout_split(names, 0) == (sorted(range(17), key=lambda i: names[i]), [])


def _toy_params(n=6):
    torch.manual_seed(0)
    p = {"means": torch.nn.Parameter(torch.randn(n, 3)), "logit_opacities": torch.nn.Parameter(torch.randn(n))}
    opt = torch.optim.Adam([{"params": [p[k]], "name": k, "lr": 0.1} for k in p])
    (p["means"].square().sum() + p["logit_opacities"].sum()).backward()
    opt.step()
    return p, opt


def test_remove_and_append_keep_adam_state_aligned():
    p, opt = _toy_params()
    before = {k: opt.state[p[k]]["exp_avg"].clone() for k in p}
    keep = torch.tensor([True, False, True, True, False, True])
    density.remove(p, opt, keep)
    for k in p:
        assert torch.equal(opt.state[p[k]]["exp_avg"], before[k][keep])
        assert opt.param_groups[[g["name"] for g in opt.param_groups].index(k)]["params"][0] is p[k]
    density.append(p, opt, {"means": torch.ones(2, 3), "logit_opacities": torch.zeros(2)})
    assert p["means"].shape == (6, 3)
    assert torch.all(opt.state[p["means"]]["exp_avg"][4:] == 0)
    (p["means"].sum() + p["logit_opacities"].sum()).backward()
    opt.step()  # shapes agree: no error


def test_reset_opacity_caps_and_clears_moments():
    p, opt = _toy_params()
    density.reset_opacity(p, opt, cap=0.01)
    assert torch.sigmoid(p["logit_opacities"]).max() <= 0.01 + 1e-6
    assert torch.all(opt.state[p["logit_opacities"]]["exp_avg"] == 0)


def test_split_children_are_smaller_and_near_parent():
    g = torch.Generator().manual_seed(0)
    p = {"means": torch.zeros(3, 3), "log_scales": torch.log(torch.tensor([[0.1, 0.2, 0.3]] * 3)),
         "quats": torch.tensor([[1.0, 0, 0, 0]] * 3), "logit_opacities": torch.zeros(3),
         "sh_dc": torch.zeros(3, 1, 3), "sh_rest": torch.zeros(3, 0, 3)}
    kids = density.split_values(p, torch.tensor([True, False, True]), g)
    assert kids["means"].shape == (4, 3)
    assert torch.allclose(kids["log_scales"].exp(), torch.tensor([[0.1, 0.2, 0.3]]) / 1.6)
    assert (kids["means"].abs() < 5 * torch.tensor([0.1, 0.2, 0.3])).all()


def _trapezoid(y, x):
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2)   # numpy < 2 has no np.trapezoid


@pytest.mark.parametrize("o", [1e-3, 0.3, 0.9, 0.9999])
@pytest.mark.parametrize("copies", [1, 2, 7, 51])
def test_split_opacity_scale_keeps_the_integral_of_the_stacked_opacity(o, copies):
    """N copies with o' and s' stacked at one place: the same peak opacity as the original
    and, along each axis, the same integral (quadrature in float64; the hard cases are
    o near 1 with 51 copies, where the closed form alternates)."""
    on, sn = density.split_opacity_scale(torch.tensor([o], dtype=torch.float64),
                                         torch.tensor([[1.0, 0.5, 2.0]], dtype=torch.float64),
                                         torch.tensor([copies]))
    assert 1 - (1 - on.item()) ** copies == pytest.approx(o, rel=1e-12)
    for axis, s in enumerate((1.0, 0.5, 2.0)):
        x = np.linspace(-40 * s, 40 * s, 200_001)
        stacked = _trapezoid(1 - (1 - on.item() * np.exp(-0.5 * (x / sn[0, axis].item()) ** 2)) ** copies, x)
        original = _trapezoid(o * np.exp(-0.5 * (x / s) ** 2), x)
        assert stacked == pytest.approx(original, rel=1e-9)
    assert (sn <= torch.tensor([[1.0, 0.5, 2.0]], dtype=torch.float64) + 1e-15).all()   # copies never grow


def _mcmc_params(opacities):
    n = len(opacities)
    g = torch.Generator().manual_seed(1)
    p = {"means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
         "log_scales": torch.nn.Parameter(torch.full((n, 3), -2.0)),
         "quats": torch.nn.Parameter(torch.tensor([[1.0, 0, 0, 0]] * n)),
         "logit_opacities": torch.nn.Parameter(torch.logit(torch.tensor(opacities))),
         "sh_dc": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g)),
         "sh_rest": torch.nn.Parameter(torch.zeros(n, 3, 3))}
    opt = torch.optim.Adam([{"params": [p[k]], "name": k, "lr": 0.1} for k in p])
    sum(v.sum() for v in p.values()).backward()
    opt.step()
    return p, opt


def test_relocate_moves_dead_gaussians_onto_live_ones_and_clears_their_moments():
    p, opt = _mcmc_params([0.001, 0.8, 0.002, 0.5, 0.9])
    live_before = {k: v.detach()[[1, 3, 4]].clone() for k, v in p.items()}
    moved = density.relocate(p, opt, torch.Generator().manual_seed(0))
    assert moved == 2 and p["means"].shape == (5, 3)
    op = torch.sigmoid(p["logit_opacities"].detach())
    assert (op >= density.DEAD_OPACITY).all()
    for dead in (0, 2):   # a copy of a live Gaussian: same centre and colour as one of them
        src = [i for i in (1, 3, 4) if torch.equal(p["means"][dead], p["means"][i])]
        assert src and torch.equal(p["sh_dc"][dead], p["sh_dc"][src[0]])
        assert op[dead] == op[src[0]] and torch.sigmoid(live_before["logit_opacities"][[1, 3, 4].index(src[0])]) > op[dead]
        for k in p:
            assert torch.all(opt.state[p[k]]["exp_avg"][[dead, src[0]]] == 0)
    untouched = [i for i in (1, 3, 4) if not any(torch.equal(p["means"][d], p["means"][i]) for d in (0, 2))]
    for i in untouched:   # live Gaussians nobody copied keep their values and moments
        assert torch.equal(p["logit_opacities"][i], live_before["logit_opacities"][[1, 3, 4].index(i)])
        assert torch.any(opt.state[p["means"]]["exp_avg"][i] != 0)


def test_grow_appends_copies_drawn_by_opacity():
    p, opt = _mcmc_params([0.001, 0.9, 0.001, 0.001])
    o1 = float(torch.sigmoid(p["logit_opacities"][1]))
    assert density.grow(p, opt, 3, torch.Generator().manual_seed(0)) == 3
    assert p["means"].shape == (7, 3) and opt.state[p["means"]]["exp_avg"].shape == (7, 3)
    assert torch.equal(p["means"][4:], p["means"][[1, 1, 1]])   # the only live one, 4 copies in all
    op = torch.sigmoid(p["logit_opacities"].detach())
    assert 1 - (1 - op[1]) ** 4 == pytest.approx(o1, rel=1e-5)
    assert torch.all(opt.state[p["quats"]]["exp_avg"][[1, 4, 5, 6]] == 0)
    sum(v.sum() for v in p.values()).backward()
    opt.step()   # shapes agree


def test_relocation_threshold_is_a_setting(small_scene, monkeypatch):
    """Below ``relocate_opacity`` a Gaussian is relocated, and copies come only from those at
    or above it; the trainer passes its setting to both."""
    p, opt = _mcmc_params([0.05, 0.8, 0.002, 0.5, 0.9])
    assert density.relocate(p, opt, torch.Generator().manual_seed(0), dead_opacity=0.1) == 2
    assert (torch.sigmoid(p["logit_opacities"].detach()) >= 0.1).all()
    p, opt = _mcmc_params([0.3, 0.8, 0.5, 0.9])
    assert density.grow(p, opt, 4, torch.Generator().manual_seed(0), dead_opacity=0.7) == 4
    assert all(any(torch.equal(p["means"][i], p["means"][j]) for j in (1, 3)) for i in range(4, 8))
    seen = []
    for fn in ("relocate", "grow"):
        real = getattr(density, fn)
        monkeypatch.setattr(density, fn, lambda *a, real=real, **k: seen.append(k["dead_opacity"]) or real(*a, **k))
    tr = make_trainer(small_scene, tiny_cfg(strategy="mcmc", relocate_opacity=0.2, budget=260))
    tr.densify()
    assert seen == [0.2, 0.2]


def test_perturb_means_moves_only_nearly_transparent_gaussians_along_their_covariance():
    p, _ = _mcmc_params([0.9, 1e-4, 0.5, 1e-4])
    with torch.no_grad():
        p["log_scales"][3] = torch.log(torch.tensor([1.0, 1e-3, 1e-3]))   # a needle along x
        p["quats"][3] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    before = p["means"].detach().clone()
    moved = density.perturb_means(p, lr_means=1e-3, noise_lr=5e2, generator=torch.Generator().manual_seed(0))
    assert moved == 2
    d = p["means"].detach() - before
    assert torch.equal(d[[0, 2]], torch.zeros(2, 3))
    assert d[1].abs().max() > 0 and d[3].abs().max() > 0
    assert d[3, 0].abs() > 1e3 * d[3, 1:].abs().max()   # Sigma @ eps: the needle's own axis


def test_regulariser_gradient_is_autograds(small_scene):
    """The closed-form gradient of the MCMC terms equals autograd's on the Gaussians in view
    and is zero elsewhere."""
    tr = make_trainer(small_scene, tiny_cfg(strategy="mcmc", opacity_reg=0.3, scale_reg=0.7))
    n = tr.params["means"].shape[0]
    in_view = torch.rand(n, generator=torch.Generator().manual_seed(2)) > 0.4
    value = tr._regulariser_grad(in_view)
    op, ls = tr.params["logit_opacities"], tr.params["log_scales"]
    x, y = op.detach().double().requires_grad_(True), ls.detach().double().requires_grad_(True)
    ref = 0.3 * torch.sigmoid(x[in_view]).sum() / n + 0.7 * y[in_view].exp().sum() / (3 * n * tr.extent)
    ref.backward()
    assert value == pytest.approx(float(ref), rel=1e-6)
    assert torch.allclose(op.grad.double(), x.grad, rtol=1e-5, atol=1e-12)
    assert torch.allclose(ls.grad.double(), y.grad, rtol=1e-5, atol=1e-12)
    assert torch.all(op.grad[~in_view] == 0)


def test_density_default_is_declared_once_and_every_entry_takes_it():
    """The trainer's config, the default preset and the command line (every mode) train with
    DEFAULT_STRATEGY and that strategy's own settings."""
    from recgs_addon.cli import build_parser
    from recgs_addon.core.train.config import TrainConfig
    from recgs_addon.core.train.strategies import DEFAULT_STRATEGY, MCMC, STRATEGIES

    assert TrainConfig().strategy == preset("default").strategy == DEFAULT_STRATEGY == "adc"
    assert preset("default").density == STRATEGIES[DEFAULT_STRATEGY]()
    parser = build_parser()
    for mode in ("3dgs", "recgs", "filter2d", "joint", "oracle"):
        args = parser.parse_args(["train", "scene", "--out", "o", "--mode", mode])
        assert preset("default", strategy=args.density).strategy == DEFAULT_STRATEGY
    args = parser.parse_args(["train", "scene", "--out", "o", "--density", "mcmc"])
    assert preset("default", strategy=args.density).density == MCMC()


def test_strategies_own_their_settings_and_checkpoints_keep_them():
    """A strategy's settings go to it by name (and only to it); a config saved in a checkpoint
    comes back with its strategy, from the nested form or the flat one of older checkpoints."""
    from dataclasses import asdict

    from recgs_addon.core.train.config import TrainConfig
    from recgs_addon.core.train.strategies import CloneSplit, MCMC

    cfg = preset("default", strategy="mcmc", relocate_opacity=0.2, draw="gradient")
    assert cfg.density == MCMC(relocate_opacity=0.2, draw="gradient")
    assert cfg.density.uses_gradient_stats() and cfg.density.regularisers() == (0.01, 0.01)
    assert TrainConfig.from_dict(asdict(cfg)) == cfg
    with pytest.raises(RecGSError, match="relocate_opacity: not a setting of density control 'adc'"):
        preset("default", relocate_opacity=0.2)
    with pytest.raises(RecGSError, match="unknown density strategy"):
        preset("default", strategy="grow")
    flat = {k: v for k, v in asdict(preset("default")).items() if k != "density"}
    old_mcmc = {**flat, "strategy": "mcmc", "opacity_reg": 0.0, "relocate_opacity": 0.005, "mcmc_draw": "gradient",
                "pixels_per_gaussian": 36.0, "densify_grad_threshold": 2e-4}
    assert TrainConfig.from_dict(old_mcmc).density == MCMC(opacity_reg=0.0, relocate_opacity=0.005, draw="gradient",
                                                           prune_weight=0.0)
    old_adc = {**flat, "strategy": "adc", "densify_grad_threshold": 3e-4, "pixels_per_gaussian": 8.0,
               "surface_pixels_per_gaussian": 3.5, "relocate_opacity": 0.005}
    # saved before significance pruning: resumed without it
    assert TrainConfig.from_dict(old_adc).density == CloneSplit(grad_threshold=3e-4, surface_pixels_per_gaussian=3.5,
                                                                prune_weight=0.0)


def test_mcmc_strategy_trains_within_its_budget(small_scene):
    cfg = tiny_cfg(strategy="mcmc", opacity_reg=0.01, scale_reg=0.01, budget=260, growth_rate=0.25)
    tr = make_trainer(small_scene, cfg)
    start = tr.evaluate()["psnr"]
    tr.run()
    assert tr.params["means"].shape[0] == 260
    assert tr.evaluate()["psnr"] > start + 1.0


def test_training_improves_and_is_deterministic(small_scene):
    a = make_trainer(small_scene, tiny_cfg())
    start = a.evaluate()["psnr"]
    a.run()
    end = a.evaluate()["psnr"]
    assert end > start + 1.0, (start, end)
    b = make_trainer(small_scene, tiny_cfg())
    b.run()
    for k in a.params:
        assert torch.equal(a.params[k], b.params[k]), k


@pytest.mark.skipif(__import__("recgs_addon.core.train.numba_ssim", fromlist=["load"]).load() is None,
                    reason="numba is not installed here")
def test_numba_path_takes_numba_ssim_with_the_same_loss(small_scene, monkeypatch):
    """On numba's path a step's SSIM goes through numba's kernels (the eager path's loss to
    float32 rounding, from the same state); on the eager path it stays eager."""
    from recgs_addon.core.train import numba_ssim
    calls = []
    real = numba_ssim.ssim_term
    monkeypatch.setattr(numba_ssim, "ssim_term", lambda *a, **k: calls.append(1) or real(*a, **k))
    losses = {}
    for path in (False, "numba"):
        tr = make_trainer(small_scene, tiny_cfg(pyramid=()))
        tr.compiler.compiled = lambda path=path: path
        losses[path] = tr.train_step()
        assert len(calls) == (path == "numba")
    assert losses["numba"] == pytest.approx(losses[False], rel=1e-5)


def test_numba_path_step_gives_torch_threads_to_the_kernels(small_scene, monkeypatch):
    """On numba's path a step runs torch on one thread and numba's kernels on the threads torch
    had (numba_kernels.own_threads: torch's spinning OpenMP threads would take their cores),
    gives torch its count back after the step, also when the step fails, and changes the
    step's numbers by float rounding only; the eager path leaves both counts alone."""
    from recgs_addon.core.render import numba_kernels
    from recgs_addon.core.train import trainer as trainer_module
    seen, fail = [], []
    real_render = trainer_module.render

    def spy(*a, **k):
        seen.append((torch.get_num_threads(), numba_kernels.threads()))
        if fail:
            raise RuntimeError("render failed")
        return real_render(*a, **k)

    monkeypatch.setattr(trainer_module, "render", spy)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        losses = {}
        for path in (False, "numba"):
            tr = make_trainer(small_scene, tiny_cfg(pyramid=()))
            tr.compiler.compiled = lambda path=path: path
            losses[path] = tr.train_step()
            assert torch.get_num_threads() == 2 and numba_kernels.threads() == 2
        assert seen == [(2, 2), (1, 2)]
        assert losses["numba"] == pytest.approx(losses[False], rel=1e-5)
        fail.append(1)
        with pytest.raises(RuntimeError, match="render failed"):
            tr.train_step()
        assert torch.get_num_threads() == 2 and numba_kernels.threads() == 2
    finally:
        torch.set_num_threads(before)


def test_state_dict_resume_is_exact(small_scene):
    full = make_trainer(small_scene, tiny_cfg())
    full.run()
    part = make_trainer(small_scene, tiny_cfg())
    assert part.run(should_stop=lambda: part.step >= 70) == "stopped"
    state = part.state_dict()
    resumed = make_trainer(small_scene, tiny_cfg())
    resumed.load_state_dict(state)
    resumed.run()
    assert resumed.step == full.step
    for k in full.params:
        assert torch.equal(full.params[k], resumed.params[k]), k


def test_fused_adam_matches_foreach_and_old_checkpoints_resume_fused(small_scene, monkeypatch):
    """The trainer's fused Adam gives foreach Adam's numbers (to float rounding), and a
    checkpoint saved by a foreach optimiser resumes with the fused one."""
    fused = make_trainer(small_scene, tiny_cfg(iterations=60))
    assert all(g["fused"] for g in fused.optimizer.param_groups)
    fused.run()
    real_adam = torch.optim.Adam

    def foreach_adam(*args, fused=None, **kw):
        return real_adam(*args, **kw)

    monkeypatch.setattr(torch.optim, "Adam", foreach_adam)
    plain = make_trainer(small_scene, tiny_cfg(iterations=60))
    assert not any(g.get("fused") for g in plain.optimizer.param_groups)
    assert plain.run(should_stop=lambda: plain.step >= 30) == "stopped"
    state = copy.deepcopy(plain.state_dict())   # the live state dict shares Adam's state
    plain.run()
    for k in fused.params:
        assert fused.params[k].shape == plain.params[k].shape, k
        assert torch.allclose(fused.params[k], plain.params[k], rtol=1e-4, atol=1e-5), k
    monkeypatch.setattr(torch.optim, "Adam", real_adam)
    resumed = make_trainer(small_scene, tiny_cfg(iterations=60))
    resumed.load_state_dict(state)
    assert all(g["fused"] for g in resumed.optimizer.param_groups)
    resumed.run()
    for k in fused.params:
        assert torch.allclose(resumed.params[k], plain.params[k], rtol=1e-4, atol=1e-5), k


@pytest.mark.parametrize("strategy", ["adc", "mcmc"])
def test_row_sparse_gradients_train_exactly_like_autograd(small_scene, strategy):
    """RowGrads (gradients only at the rows in view, persistent buffers) trains bit for bit
    like plain autograd's full-size index_select backward: through densification, pruning, an
    opacity reset and SH degrees rising from 0 (the rest block joins the optimiser late); with
    mcmc, through relocation and the regularisers (differentiated on the rows in view both ways)."""
    kw = dict(sh_policy="schedule", sh_every=30, sh_degree=2, opacity_reset_every=60, iterations=100,
              strategy=strategy, budget=300)
    sparse = make_trainer(small_scene, tiny_cfg(**kw))
    partial = []
    write = sparse.row_grads.write

    def spy():
        ids = sparse.row_grads._leaves["means"][2]
        partial.append(ids.shape[0] < sparse.params["means"].shape[0])
        write()
    sparse.row_grads.write = spy
    sparse.run()
    plain = make_trainer(small_scene, tiny_cfg(**kw))
    plain.row_grads = RowGrads(sparse=False)
    plain.run()
    assert (any(partial) or strategy == "mcmc") and sparse.sh_degree == 2
    assert len(sparse.params["means"]) != len(make_trainer(small_scene, tiny_cfg(**kw)).params["means"])
    for k in plain.params:
        assert torch.equal(sparse.params[k], plain.params[k]), k
    for ps, pp in zip(sparse.optimizer.param_groups, plain.optimizer.param_groups):
        ss, sp = sparse.optimizer.state[ps["params"][0]], plain.optimizer.state[pp["params"][0]]
        assert ss.keys() == sp.keys(), ps["name"]
        for key in ss:
            assert torch.equal(ss[key], sp[key]), (ps["name"], key)


def test_row_grads_refuses_two_row_sets_and_leaves_untouched_params_alone():
    means = torch.nn.Parameter(torch.randn(10, 3))
    other = torch.nn.Parameter(torch.randn(10, 3))
    rg = RowGrads()
    m = rg.track("means", means)
    rg.track("other", other)
    a = rg(m, torch.tensor([1, 4]))
    assert rg(m, torch.tensor([1, 4])) is a
    with pytest.raises(ValueError, match="two different row sets"):
        rg(m, torch.tensor([2, 4]))
    (a ** 2).sum().backward()
    rg.write()
    assert other.grad is None
    expected = torch.zeros(10, 3)
    expected[[1, 4]] = 2 * means.detach()[[1, 4]]
    assert torch.equal(means.grad, expected)
    means.grad = None                       # the optimiser's zero_grad(set_to_none=True)
    m = rg.track("means", means)
    (rg(m, torch.tensor([7])) * 3).sum().backward()
    rg.write()
    expected = torch.zeros(10, 3)
    expected[7] = 3.0
    assert torch.equal(means.grad, expected)     # last step's rows were cleared


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc allocator tuning")
def test_job_allocator_keeps_freed_memory():
    """A training job keeps the memory it frees (glibc: no mmap, no trim): re-running a
    pattern of 12-64 MB allocations faults in almost no new pages, where glibc's defaults
    (RECGS_MALLOC=system) fault them all in again every time."""
    code = ("import resource, torch\n"
            "from recgs_addon.commands.train import tune_allocator\n"
            "print(tune_allocator())\n"
            "def work():\n"
            "    for n in (3 << 20, 10 << 20, 16 << 20, 7 << 20):\n"
            "        a = torch.ones(n); b = torch.ones(n // 2); del a; c = torch.ones(n); del b, c\n"
            "work(); work(); work()   # the heap grows to the pattern's peak\n"
            "f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "for _ in range(3): work()\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)\n")
    faults = {}
    for mode in ("retained", "system"):
        env = dict(os.environ, RECGS_MALLOC="" if mode == "retained" else "system", OMP_NUM_THREADS="1")
        r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr
        done, n = r.stdout.split()
        assert done == mode
        faults[mode] = int(n)
    assert faults["system"] > 50_000, faults          # 4k pages per 16 MB, 36 allocations of 6-64 MB
    assert faults["retained"] < faults["system"] / 8, faults


@pytest.mark.parametrize("kwargs,msg", [
    ({"budget": 0}, "budget must be at least 1"),
    ({"downscale": 8}, "below 8 px"),
    ({"strategy": "mcmc", "relocate_opacity": 1.0}, "relocate_opacity must be between 0 and 1"),
    ({"prune_weight": -1.0}, r"--prune-weight must be 0 \(off\)"),
    ({"prune_weight": float("nan")}, r"--prune-weight must be 0 \(off\)"),
    ({"prune_share": 0.0}, r"prune_share in \(0, 1\]"),
])
def test_bad_settings_refused_before_work(small_scene, kwargs, msg):
    with pytest.raises(RecGSError, match=msg):
        make_trainer(small_scene, tiny_cfg(**kwargs))


def _train_cmd(scene, out, *extra):
    return [sys.executable, "-m", "recgs_addon", "train", str(scene), "--out", str(out), "--eager",
            "--holdout-every", "4", *extra]


def _run(cmd, **kw):
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, **kw)


def test_job_bad_inputs_give_clear_errors(small_scene, tmp_path):
    empty = tmp_path / "empty_scene"
    import shutil

    shutil.copytree(small_scene, empty)
    shutil.rmtree(empty / "images")
    (empty / "images").mkdir()
    cases = [
        (_train_cmd(empty, tmp_path / "o1"), "images: image folder is empty"),
        (_train_cmd(small_scene, tmp_path / "o2", "--images", str(tmp_path)), "none of the 8 images"),
        (_train_cmd(small_scene, tmp_path / "o3", "--budget", "0"), "budget must be at least 1"),
        (_train_cmd(small_scene, tmp_path / "o4", "--downscale", "16"), "below 8 px"),
        (_train_cmd(small_scene, tmp_path / "o5", "--resume"), "no checkpoint to resume from"),
    ]
    for cmd, msg in cases:
        r = _run(cmd)
        assert r.returncode == 1, (cmd, r.stderr)
        assert msg in r.stderr, (msg, r.stderr)
        events = [json.loads(line) for line in r.stdout.splitlines()]
        assert events[-1]["event"] == "error" and msg in events[-1]["message"]
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o3").exists()


def _final_psnr(out):
    return json.loads((out / "metrics.json").read_text())["psnr_test"]


@pytest.mark.slow
def test_sigkill_then_resume_matches_uninterrupted(small_scene, tmp_path):
    args = ("--iterations", "160", "--checkpoint-every", "0")
    ref = _run(_train_cmd(small_scene, tmp_path / "ref", *args))
    assert ref.returncode == 0, ref.stderr
    out = tmp_path / "killed"
    proc = subprocess.Popen(_train_cmd(small_scene, out, *args), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    rng = np.random.default_rng()
    target = int(rng.integers(30, 120))
    for line in proc.stdout:
        ev = json.loads(line)
        if ev["event"] == "checkpoint" and ev["iteration"] >= target:
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    r = _run(_train_cmd(small_scene, out, "--resume"))
    assert r.returncode == 0, r.stderr
    assert abs(_final_psnr(out) - _final_psnr(tmp_path / "ref")) < 0.1


@pytest.mark.slow
def test_checkpoint_never_half_written(small_scene, tmp_path):
    """Kill the job at random moments while it checkpoints every step: the file under the
    final name always loads."""
    from recgs_addon.core.train.checkpoint import load_checkpoint

    out = tmp_path / "o"
    rng = np.random.default_rng(1)
    loaded = 0
    for _ in range(4):
        proc = subprocess.Popen(_train_cmd(small_scene, out, "--iterations", "100000", "--checkpoint-every", "0",
                                           *(["--resume"] if (out / "checkpoint.pt").exists() else [])),
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 120
        while not (out / "checkpoint.pt").exists() and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(float(rng.uniform(0.2, 1.5)))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        state = load_checkpoint(out / "checkpoint.pt")
        assert state["step"] > 0
        loaded += 1
    assert loaded == 4
    assert not [p for p in os.listdir(out) if p.endswith(".tmp") and not p.startswith(".")]


def test_sigterm_checkpoints_and_exits_cleanly(small_scene, tmp_path):
    out = tmp_path / "o"
    proc = subprocess.Popen(_train_cmd(small_scene, out, "--iterations", "100000", "--checkpoint-every", "1000"),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in proc.stdout:
        if json.loads(line).get("event") == "progress":
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stdout.read()
    assert proc.wait(timeout=120) == 0
    done = [json.loads(x) for x in rest.splitlines() if x.strip()][-1]
    assert done["event"] == "done" and done["status"] == "cancelled"
    from recgs_addon.core.train.checkpoint import load_checkpoint
    from recgs_addon.core.io.ply import read_gaussian_ply

    assert load_checkpoint(out / "checkpoint.pt")["step"] == done["iteration"]
    assert len(read_gaussian_ply(out / "point_cloud.ply")) > 0


def test_render_command(small_scene, tmp_path):
    from recgs_addon.core.model.gaussians import init_from_points
    from recgs_addon.core.io.colmap import load_scene
    from recgs_addon.core.io.ply import write_gaussian_ply

    sc = load_scene(small_scene)
    write_gaussian_ply(tmp_path / "m.ply", init_from_points(sc.points, sc.colors))
    r = _run([sys.executable, "-m", "recgs_addon", "render", str(tmp_path / "m.ply"), str(small_scene),
              "--out", str(tmp_path / "r"), "--names", "view_001.png,view_002.png", "--eager"])
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "view_001.exr", "view_001.png", "view_002.exr", "view_002.png"]
    done = json.loads(r.stdout.splitlines()[-1])
    assert done["views"] == 2 and done["mean_psnr"] > 5


def test_keep_best_ends_with_the_best_held_out_model(small_scene):
    """The run ends with the model that scored best on the held-out photos, at an evaluation
    not right after a densification; keep_best off ends with the last one."""
    cfg = tiny_cfg(iterations=240, eval_every=20, keep_best=True)
    tr = make_trainer(small_scene, cfg)
    # pretend an early model scores far better than any later one
    tr.train_until(until=lambda: tr.step >= 60)
    tr.best = {"score": 99.0, "step": tr.step, **tr.snapshot()}
    kept = {n: v.detach().clone() for n, v in tr.params.items()}
    tr.run()
    assert tr.best_step == 60
    for n in kept:
        assert torch.equal(tr.params[n].detach(), kept[n]), n
    # an evaluation within half a densification interval after a densification is not considered
    tr.best = None
    tr.last_densify = tr.step - cfg.densify_every // 2 + 1
    tr._consider_best(50.0)
    assert tr.best is None
    tr.last_densify = tr.step - cfg.densify_every // 2
    tr._consider_best(50.0)
    assert tr.best["score"] == 50.0 and tr.best["step"] == tr.step

    last = make_trainer(small_scene, tiny_cfg(iterations=240, eval_every=20, keep_best=False))
    last.run()
    assert last.best is None and last.best_step is None and last.step == 240


def test_keep_best_under_moving_light_chooses_only_from_the_later_half(small_scene):
    """Where the photos carry moving light (or the run models the water) an early, blurred model
    that scores best on the held-out photos is not kept: only models trained half the run or
    more are candidates; without either, any evaluation is."""
    from recgs_addon.core.train.evaluation import BEST_FROM_SHARE

    tr = make_trainer(small_scene, tiny_cfg(iterations=240, eval_every=20, keep_best=True))
    assert tr.best_from_share() == 0.0
    tr.light = {"caustics": True}
    assert tr.best_from_share() == BEST_FROM_SHARE
    tr.train_until(until=lambda: tr.step >= 60)
    tr.best = None
    tr._consider_best(99.0)            # a quarter of the run: not a candidate
    assert tr.best is None
    tr.train_until(until=lambda: tr.step >= 120)
    tr._consider_best(40.0)
    assert tr.best["step"] == 120
    tr.run()
    assert tr.best_step is None or tr.best_step >= 120
    # a time limit counts the share in time
    tr.cfg.max_minutes = 1.0
    tr.elapsed = 20.0
    assert tr.run_share() == 20.0 / 60.0


def test_density_control_ends_before_the_time_limit_so_the_last_gaussians_settle(small_scene):
    tr = make_trainer(small_scene, tiny_cfg(iterations=240, max_minutes=1.0, densify_until_share=0.8))
    tr.step = tr.cfg.densify_from + 1
    tr.elapsed = 0.5 * 60.0
    assert tr.densifying()
    tr.elapsed = 0.81 * 60.0
    assert not tr.densifying() and tr.growth_over()
    tr.cfg.densify_until_share = 1.0          # density control to the end
    assert tr.densifying()
    tr.cfg.max_minutes = None                 # without a time limit the steps decide
    tr.cfg.densify_until_share = 0.8
    assert tr.densifying()
    tr.step = tr.cfg.densify_until
    assert not tr.densifying()


def test_blending_weights_add_up_to_the_alpha_of_the_view(small_scene):
    from recgs_addon.core.outputs.diagnostics import blending_weights, support_summary, view_support
    from recgs_addon.core.render.rasterizer import render
    from recgs_addon.core.train.data import view_tensors

    tr = make_trainer(small_scene, tiny_cfg(iterations=60))
    tr.run()
    i = tr.data.train_ids[0]
    w = blending_weights(tr, i)
    cam, _ = tr.data.view(i, 1)
    viewmat, K = view_tensors(cam, tr.device)
    p = tr.params
    with torch.no_grad():
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], tr._sh(), viewmat, K,
                     cam.width, cam.height, sh_degree=tr.sh_degree, compiled=False)
    # alpha = 1 - T_final = sum_i alpha_i T_i over the Gaussians of each pixel
    assert float(w.sum()) == pytest.approx(float(out.alpha.sum()), rel=1e-3)
    assert float(w.min()) >= -1e-5
    # rendered at half size, the weights still count training-resolution pixels (within what the
    # rasterizer's fixed screen-space blur of 0.3 px adds to each Gaussian at a quarter of the pixels)
    half = blending_weights(tr, i, max_side=max(cam.width, cam.height) // 2)
    assert float(half.sum()) == pytest.approx(float(out.alpha.sum()), rel=0.2)
    support = view_support(tr)
    assert support.shape == (p["means"].shape[0],) and 0 <= support.min() and support.max() <= len(tr.data.train_ids)
    s = support_summary(support)
    assert sum(s["histogram"]) == len(support) and 0 <= s["share_le2"] <= 1


def test_job_with_an_image_that_does_not_decode_stops_with_one_line(small_scene, tmp_path):
    """A truncated PNG passes the import's header check; the job that then reads it stops with
    one error line naming the file (no traceback) and exit code 1."""
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    victim = sorted((scene / "images").iterdir())[1]
    victim.write_bytes(victim.read_bytes()[:200])
    r = _run(_train_cmd(scene, tmp_path / "out"))
    assert r.returncode == 1, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    err = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and victim.name in err[0] and "cannot decode" in err[0], r.stderr[-2000:]
    # libpng writes its own complaint to stdout; the job's events are the JSON lines
    events = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert events[-1]["event"] == "error" and victim.name in events[-1]["message"]


def test_an_image_the_run_would_meet_late_stops_it_before_it_writes(small_scene, tmp_path):
    """Regression (outside trial): a cut-off PNG that a short run never trained on was first
    read while the run wrote its outputs: a traceback, and a checkpoint, a PLY and half the
    renders left in the folder. Every image is now read before the job writes anything: a
    new job leaves no folder, and a resume leaves the last checkpoint as it was."""
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    out = tmp_path / "out"
    assert _run(_train_cmd(scene, out, "--iterations", "2")).returncode == 0
    files = sorted(p.relative_to(out) for p in out.rglob("*"))
    checkpoint = (out / "checkpoint.pt").read_bytes()
    victim = sorted((scene / "images").iterdir())[-1]          # a training view
    victim.write_bytes(victim.read_bytes()[:300])
    for target, extra in ((tmp_path / "fresh", ("--iterations", "1")), (out, ("--resume", "--iterations", "4"))):
        r = _run(_train_cmd(scene, target, *extra))
        assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
        err = [line for line in r.stderr.splitlines() if line.startswith("error:")]
        assert err == [f"error: {victim}: cannot decode image pixels (Read error: hit end of file in png reader)"], err
    assert not (tmp_path / "fresh").exists()
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == files
    assert (out / "checkpoint.pt").read_bytes() == checkpoint


def test_a_failure_while_writing_the_outputs_is_one_line_and_keeps_the_checkpoint(small_scene, tmp_path):
    """Outputs written at the end of a run (renders, metrics, report) that cannot be written
    end the job with one error line, exit code 1, and the final checkpoint in place."""
    from recgs_addon.core.train.checkpoint import load_checkpoint

    out = tmp_path / "out"
    out.mkdir()
    (out / "renders").write_text("a file where the renders folder goes")
    r = _run(_train_cmd(small_scene, out, "--iterations", "3"))
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    err = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert err == [f"error: {out / 'renders'}: is a file, not a folder (choose another folder)"], err
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 3
    events = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert events[-1]["event"] == "error" and "the last checkpoint is kept" in events[-1]["message"]


# ------------------------------------------------------------------ NaN / Inf guards

def test_nan_loss_skips_the_step_then_stops_the_run(small_scene, monkeypatch):
    from recgs_addon.core.train import trainer as trainer_mod
    tr = make_trainer(small_scene, tiny_cfg(iterations=40))
    for _ in range(3):
        tr.train_step()
    before = {n: v.detach().clone() for n, v in tr.params.items()}
    real = trainer_mod.training_loss
    monkeypatch.setattr(trainer_mod, "training_loss", lambda *a, **k: real(*a, **k) * float("nan"))
    assert math.isnan(tr.train_step())
    assert all(torch.equal(before[n], v) for n, v in tr.params.items())      # no update
    assert tr.skipped_steps == 1 and tr.step == 4
    with pytest.raises(trainer_mod.TrainingDiverged, match="loss was nan for 10 steps in a row"):
        for _ in range(20):
            tr.train_step()
    monkeypatch.setattr(trainer_mod, "training_loss", real)
    tr.bad_steps = 0
    tr.train_step()                                                           # recovers
    assert all(bool(torch.isfinite(v).all()) for v in tr.params.values())


def test_nan_parameters_are_never_checkpointed(small_scene, tmp_path):
    from recgs_addon.core.train.checkpoint import load_checkpoint, save_checkpoint
    from recgs_addon.core.train.trainer import TrainingDiverged
    tr = make_trainer(small_scene, tiny_cfg(iterations=40))
    for _ in range(5):
        tr.train_step()
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, tr.state_dict())
    with torch.no_grad():
        tr.params["log_scales"][3, 1] = float("inf")
    with pytest.raises(TrainingDiverged, match="1 Gaussians have NaN/Inf in 'log_scales' at step 5"):
        save_checkpoint(path, tr.state_dict())
    assert load_checkpoint(path)["step"] == 5 and torch.isfinite(load_checkpoint(path)["params"]["log_scales"]).all()
    with torch.no_grad():
        tr.params["log_scales"][3, 1] = 0.0
    tr.optimizer.state[tr.params["means"]]["exp_avg_sq"][0, 0] = float("nan")
    with pytest.raises(TrainingDiverged, match="exp_avg_sq of 'means'"):
        tr.check_finite()


@pytest.mark.slow
def test_long_run_stays_finite():
    """20,000 steps on the sample survey (at quarter size, at most 5,000 Gaussians, to keep it to
    minutes) with a watch on every step: the loss, every gradient before Adam uses it, and,
    every 100 steps, every parameter and Adam moment must be finite; no step may be skipped."""
    cfg = preset("default", iterations=20_000, downscale=4, budget=5_000, compiled=False, holdout_every=8,
                 eval_every=1000, log_every=100)
    tr = make_trainer(ROOT / "data" / "sample", cfg)
    bad = []
    step = tr.optimizer.step

    def watched_step(*a, **k):
        for g in tr.optimizer.param_groups:
            for p in g["params"]:
                if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                    bad.append((tr.step, g["name"]))
        return step(*a, **k)

    tr.optimizer.step = watched_step
    losses = []
    while tr.step < cfg.iterations:
        if tr.optimizer.step is not watched_step:
            step = tr.optimizer.step             # densification made a new optimiser: watch it too
            tr.optimizer.step = watched_step
        losses.append(tr.train_step())
        if tr.step % 100 == 0:
            tr.check_finite()
    assert not bad, bad[:5]
    assert tr.skipped_steps == 0 and all(math.isfinite(v) for v in losses)
    assert np.mean(losses[-500:]) < np.mean(losses[:500])


def test_photos_are_kept_compact_at_their_training_size(small_scene):
    """Each photo is decoded once at its training size and kept as uint8 (a fourth of float32);
    views hand out float32 in [0, 1] with the camera scaled to the image."""
    from recgs_addon.core.io.images import read_image

    tr = make_trainer(small_scene, tiny_cfg(max_side=20))        # the 40x30 photos, long side capped at 20
    data = tr.data
    data.load_all(2)
    i = data.train_ids[0]
    cam, img = data.view(i)
    assert (cam.width, cam.height) == (20, 15) and img.shape == (15, 20, 3) and img.dtype == torch.float32
    full = data.scene.cameras[i]
    assert cam.fx == pytest.approx(full.fx / 2) and cam.cx == pytest.approx(full.cx / 2)
    assert data.photo(i).dtype == torch.uint8
    ref = read_image(data.scene.image_path(full), size=(20, 15))
    assert np.abs(img.numpy() - ref).max() <= 0.5 / 255 + 1e-6     # the box filter's average, rounded to 8 bits
    cam2, img2 = data.view(i, 2)                                    # the pyramid: area averages of that size
    assert img2.shape == (8, 10, 3) and (cam2.width, cam2.height) == (10, 8) and img2.dtype == torch.float32
    from recgs_addon.core.train.data import as_float, resample
    exact = resample(as_float(data.photo(i)).double(), 8, 10)      # kept as float16: within its rounding
    assert (img2.double() - exact).abs().max() <= 2 ** -12
    photos = len(data.train_ids) + len(data.test_ids)
    assert data.image_bytes() == photos * 15 * 20 * 3 + len(data.train_ids) * 8 * 10 * 3 * 2
    assert make_trainer(small_scene, tiny_cfg()).data.camera(i).width == 40   # 1600 leaves small photos alone


def test_dry_steps_time_the_step_and_change_nothing(small_scene):
    from recgs_addon.core.train.plan import time_steps

    tr = make_trainer(small_scene, tiny_cfg())
    for _ in range(3):
        tr.train_step()
    before = tr.state_dict()
    seconds, path = time_steps(tr, 2)
    assert seconds > 0 and path == "eager"
    after = tr.state_dict()
    for n in before["params"]:
        assert torch.equal(before["params"][n], after["params"][n]), n
    assert all(p.grad is None for p in tr.params.values())
    assert before["order"] == after["order"] and torch.equal(before["gen"], after["gen"])
    assert before["np_rng"] == after["np_rng"] and before["step"] == after["step"]


def test_job_says_its_plan_and_refuses_what_cannot_fit(small_scene, tmp_path):
    """Before any training a job emits its plan (resolution, images, memory, time per 1,000
    steps). Memory too small for the images themselves, or for a budget the user set: the
    job refuses with one line naming the survey and saying what to do, and writes nothing."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    r = _run(_train_cmd(small_scene, tmp_path / "ok", "--iterations", "2"), env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    events = [json.loads(line) for line in r.stdout.splitlines()]
    plan = next(e for e in events if e["event"] == "plan")
    start = next(i for i, e in enumerate(events) if e["event"] == "start")
    assert events.index(plan) < start
    # the worker's threads sleep while they wait (spinning ones starve a busy machine)
    assert events[start]["threads"]["wait"] == "PASSIVE" and events[start]["threads"]["torch"] >= 1
    assert (plan["width"], plan["height"], plan["train_views"], plan["test_views"]) == (40, 30, 6, 2)
    assert plan["seconds_per_1000"] > 0 and plan["peak_bytes"] > plan["image_bytes"] > 0
    assert plan["lines"][0].startswith("training at 40x30: 6 training and 2 held-out views")
    assert any(line.startswith("time: about") for line in plan["lines"])
    assert plan["peak_bytes"] >= plan["start_bytes"] > plan["image_bytes"]
    mem = next(line for line in plan["lines"] if line.startswith("memory:"))
    assert (f"at most {plan['peak_bytes'] / 2 ** 30:.1f} GB if the model grows to {plan['budget']:,} Gaussians"
            in mem) == (plan["budget"] > plan["gaussians"]), mem
    for extra, msg in ((("--max-memory", "0.01"), "need about"),
                       (("--max-memory", "4", "--budget", "10000000"), "ask for at most")):
        out = tmp_path / f"refused{len(extra)}"
        r = _run(_train_cmd(small_scene, out, "--iterations", "2", *extra))
        assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
        err = [line for line in r.stderr.splitlines() if line.startswith("error:")]
        assert len(err) == 1 and msg in err[0] and str(small_scene) in err[0], err
        assert not out.exists()


def test_automatic_budget_follows_the_seabed_the_views_hold(small_scene):
    """An automatic budget: training pixels over the median views of a sparse point over
    surface_pixels_per_gaussian, unless training pixels over pixels_per_gaussian is smaller;
    never below the Gaussians a run starts with."""
    from recgs_addon.core.train.coverage import sparse_coverage
    from recgs_addon.core.train.trainer import auto_budget

    tr = make_trainer(small_scene, tiny_cfg(pixels_per_gaussian=0, surface_pixels_per_gaussian=0.01))
    pixels, views = tr.data.training_pixels(), sparse_coverage(tr.data).median_views
    assert views > 1 and pixels == 6 * 40 * 30
    assert tr.budget == int(pixels / views / 0.01) == auto_budget(tr.data, tr.cfg)
    both = tiny_cfg(pixels_per_gaussian=0.1, surface_pixels_per_gaussian=0.01)
    assert auto_budget(tr.data, both) == int(min(pixels / 0.1, pixels / views / 0.01))
    assert auto_budget(tr.data, tiny_cfg(pixels_per_gaussian=0, surface_pixels_per_gaussian=0)) is None
    assert make_trainer(small_scene, tiny_cfg(surface_pixels_per_gaussian=1e6)).budget == len(tr.data.scene.points)


def test_plan_caps_an_automatic_budget_to_the_memory_there_is(small_scene):
    from recgs_addon.core.train import plan as planning

    tr = make_trainer(small_scene, tiny_cfg(pixels_per_gaussian=0.01, surface_pixels_per_gaussian=0))   # 720,000
    tr.data.load_all()
    n, auto = int(tr.params["means"].shape[0]), tr.budget
    assert auto == 720_000
    fixed = planning.estimate_peak(planning.resident_bytes(), 40 * 30, 0, 3, n, n)
    p = planning.plan_run(tr, limit_bytes=fixed + planning.gaussian_bytes(3) * 100_000, warmup_steps=0)
    assert p.budget_capped_from == auto and 90_000 < p.budget == tr.budget < 110_000
    assert "capped at" in p.lines()[-1]


def test_time_between_segments_counts_against_the_limit(small_scene):
    """Every second from the clock's start counts: work a driving method does between training
    segments (renders, estimates) and the time before the first step alike."""
    import time as _time

    tr = make_trainer(small_scene, tiny_cfg(iterations=10 ** 6, max_minutes=0.02))   # 1.2 s
    origin = _time.perf_counter() - 0.5          # the command started half a second ago
    tr.start_clock(origin)
    assert tr.train_until(until=lambda: tr.step >= 3) == "until"
    assert tr.elapsed >= 0.5
    _time.sleep(1.0)                             # work between segments
    steps = tr.step
    assert tr.train_until() == "time limit"
    assert tr.step == steps                      # no step after the limit had passed
    assert tr.elapsed >= 1.2


def test_resumed_clock_goes_on_from_the_saved_time(small_scene):
    tr = make_trainer(small_scene, tiny_cfg(iterations=6))
    tr.run()
    state = tr.state_dict()
    again = make_trainer(small_scene, tiny_cfg(iterations=12))
    again.load_state_dict(state)
    saved = state["elapsed"]
    again.train_until()
    assert again.elapsed > saved
    assert again.elapsed < saved + 60          # counted from the resume, not from the first run's start


def test_time_limit_keeps_room_for_the_finishing(small_scene):
    """The renders a job makes after training (set by the job) come out of the time limit, at
    the latest measured render time, and the images it writes, at the measured write time; at
    most FINISH_SHARE of the limit, with the whole estimate told apart."""
    from recgs_addon.core.train.progress import FINISH_SHARE

    tr = make_trainer(small_scene, tiny_cfg(iterations=10 ** 6, max_minutes=0.05))   # 3 s
    assert tr.finishing_reserve() == 0.0
    tr.evaluate()                          # renders the held-out views: a render time
    tr.finishing_renders = lambda: 4
    renders_only = tr.finishing_estimate()
    assert 0.0 < renders_only and tr.finishing_reserve() == pytest.approx(min(renders_only, 3.0 * FINISH_SHARE))
    tr.finishing_writes, tr.write_s = (lambda: 10), 0.02   # and the images it writes: 10 at 20 ms
    assert tr.finishing_estimate() == pytest.approx(renders_only + 0.2)
    assert tr.finishing_reserve() == pytest.approx(min(renders_only + 0.2, 3.0 * FINISH_SHARE))
    tr.finishing_renders = lambda: 10 ** 6
    assert tr.finishing_reserve() == pytest.approx(3.0 * FINISH_SHARE)
    assert tr.finishing_estimate() > 100 * tr.finishing_reserve()
    assert tr.train_until() == "time limit"
    assert 3.0 * (1 - FINISH_SHARE) <= tr.elapsed < 3.0


def test_near_its_time_limit_a_run_times_a_render_of_the_model_as_it_is(small_scene):
    """The reserve for the finishing rests on the latest render's time; a render timed on the
    model the run started from (slow: its Gaussians are large) would end training early. Near
    the limit a render timed RETIME_STEPS steps ago or more is timed again, on the model as it is
    now, before the reserve decides; one timed since is trusted."""
    from recgs_addon.core.train.progress import FINISH_SHARE, RETIME_STEPS

    tr = make_trainer(small_scene, tiny_cfg(iterations=10 ** 6, max_minutes=1.0))   # 60 s
    tr.finishing_renders = lambda: 10
    tr.evaluate()
    real = tr._render_s
    assert real < 0.5
    timed = []
    render = tr.render_output
    tr.render_output = lambda *a, **k: (timed.append(tr.step), render(*a, **k))[1]
    tr._render_s = 2.0                     # as if timed on a slow start: 20 s of renders kept
    assert tr.finishing_reserve() == pytest.approx(20.0)
    tr.elapsed = 45.0                      # within the reserve of the 60-s limit
    tr.step = tr._render_step + RETIME_STEPS - 1
    assert tr.time_is_up() and timed == []               # timed lately: trusted
    tr.step += 1
    assert not tr.time_is_up() and timed == [tr.step]    # timed again: 10 renders now fit
    assert tr._render_s < 0.5 and tr.finishing_reserve() < 5.0 and tr.elapsed > 45.0
    tr.elapsed = 20.0                      # far from the limit: no render
    tr.step += RETIME_STEPS
    assert not tr.time_is_up() and timed == [tr.step - RETIME_STEPS]
    tr.elapsed = 60.0 - 0.5 * tr.finishing_reserve()
    assert tr.time_is_up()                                # within the fresh reserve: done
    assert FINISH_SHARE * 60.0 > tr.finishing_reserve()


def test_a_job_measures_what_an_output_image_takes_to_write(small_scene, tmp_path):
    """The job times a training photo written as PNG and EXR into its output folder, for the
    time limit's reserve, and leaves nothing there."""
    from recgs_addon.commands.train import _write_seconds

    tr = make_trainer(small_scene, tiny_cfg())
    seconds = _write_seconds(tmp_path, tr)
    assert 0.0 < seconds < 5.0
    assert list(tmp_path.iterdir()) == []


def test_the_write_probe_does_not_count_a_formats_first_write(small_scene, tmp_path, monkeypatch):
    """A format's first write in a process loads its libraries (slow on a fresh install); the
    finishing writes many files after it, so the probe times the second."""
    from recgs_addon.commands.train import _write_seconds
    from recgs_addon.core.io import images

    seen = set()
    write = images.write_image

    def slow_first(path, image, *a, **k):
        if path.suffix not in seen:
            seen.add(path.suffix)
            time.sleep(0.5)
        return write(path, image, *a, **k)
    monkeypatch.setattr(images, "write_image", slow_first)
    tr = make_trainer(small_scene, tiny_cfg())
    assert 0.0 < _write_seconds(tmp_path, tr) < 0.25
    assert seen == {".png", ".exr"} and list(tmp_path.iterdir()) == []


def test_progress_says_the_share_done_from_the_eta_or_the_time_limit(small_scene):
    """The share done a progress report carries (the sidebar's bar shows it as it is): before a
    step is timed, the time limit's share; then elapsed over elapsed plus the ETA."""
    tr = make_trainer(small_scene, tiny_cfg(max_minutes=2.0))
    tr.elapsed = 30.0
    assert tr.progress(0.0, {}).fraction == pytest.approx(0.25)
    tr.step, tr.elapsed = 10, 60.0      # 6 s a step, 110 steps left, but 60 s of the limit
    p = tr.progress(0.0, {})
    assert p.eta == pytest.approx(60.0) and p.fraction == pytest.approx(0.5)
    free = make_trainer(small_scene, tiny_cfg())
    free.elapsed = 30.0
    assert free.progress(0.0, {}).fraction == 0.0


def test_a_step_records_each_gaussians_peak_weight_in_training_pixels(small_scene):
    """While densifying, a step adds the view's blending weights to the statistics, counted in
    training-resolution pixels whatever the pyramid level it renders at: the weights
    diagnostics.blending_weights gives for the same model and view."""
    from recgs_addon.core.outputs.diagnostics import blending_weights

    tr = make_trainer(small_scene, tiny_cfg())
    i = tr.data.train_ids[1]
    assert tr.level() == 2 and tr.densifying()
    w, h = tr.data.sizes[i]
    expected = blending_weights(tr, i, max_side=-(-max(w, h) // 2))   # the same half-size render
    tr.order = [i]
    tr.train_step()
    peak, count = tr.stats.peak_weight, tr.stats.count
    assert float(expected.max()) > 5 and torch.allclose(peak, expected, rtol=1e-4, atol=1e-5)
    assert torch.equal(count > 0, tr.stats.max_radius > 0) and int(count.max()) == 1
    off = make_trainer(small_scene, tiny_cfg(prune_weight=0))
    off.order = [i]
    off.train_step()
    assert float(off.stats.peak_weight.abs().max()) == 0 and int(off.stats.count.max()) == 1


def test_clone_split_removes_what_no_view_needs_and_grows_in_its_room(small_scene):
    """Drawn in at least prune_views views, under prune_weight pixels in each: removed, and its
    room goes to growth at the error within the budget; too few views: kept (no evidence); a
    Gaussian with a high gradient but under twice prune_weight is not copied."""
    tr = make_trainer(small_scene, tiny_cfg(prune_weight=1.0, prune_views=3, densify_from=0))
    n = tr.params["means"].shape[0]
    tr.budget = n                       # full: only the freed room can grow
    with torch.no_grad():               # nothing transparent, nothing huge
        tr.params["logit_opacities"].fill_(2.0)
        tr.params["log_scales"].fill_(float(np.log(1e-4 * tr.extent)))
    s = tr.stats
    s.count[:] = 5
    s.peak_weight[:] = 10.0
    s.peak_weight[:4] = 0.5             # needless
    s.peak_weight[4] = 0.5
    s.count[4] = 2                      # ... but seen by too few views
    s.accum[:] = 0.0
    s.accum[10:16] = 1.0 * s.count[10:16]   # high gradient: six candidates for four places
    s.accum[16] = 1.0 * s.count[16]
    s.peak_weight[16] = 1.5             # high gradient, but its copies would supply under 1 px
    means = tr.params["means"].detach().clone()
    info = tr.densify()
    assert info["needless"] == 4 and info["cloned"] == 4 and info["split"] == 0
    assert tr.params["means"].shape[0] == n
    kept = tr.params["means"].detach()
    assert not any(torch.equal(kept[j], means[r]) for j in range(len(kept)) for r in range(4))
    assert any(torch.equal(kept[j], means[4]) for j in range(len(kept)))
    assert tr.density_totals["needless"] == 4
    young = tr.stats.young_from            # the four copies, at the end: not judged next time
    assert young == n - 4
    tr.stats.count[:] = 5
    assert torch.equal(torch.nonzero(tr.stats.needless(1.0, 3)).squeeze(1), torch.arange(young))
    off = make_trainer(small_scene, tiny_cfg(prune_weight=0, densify_from=0))
    off.stats.count[:] = 5
    assert off.densify()["needless"] == 0


def test_mcmc_relocates_what_no_view_needs():
    p, opt = _mcmc_params([0.8, 0.8, 0.5, 0.9])
    needless = torch.tensor([False, True, False, False])
    moved = density.relocate(p, opt, torch.Generator().manual_seed(0), needless=needless)
    assert moved == 1
    assert any(torch.equal(p["means"][1], p["means"][i]) for i in (0, 2, 3))


def test_needless_gaussians_go_a_share_at_a_time_the_least_significant_first(small_scene):
    tr = make_trainer(small_scene, tiny_cfg(prune_weight=1.0, prune_share=0.02))
    n = tr.params["means"].shape[0]
    most = int(0.02 * n)
    s = tr.stats
    s.count[:] = 5
    s.peak_weight[:] = 10.0
    s.peak_weight[: 3 * most] = torch.linspace(0.9, 0.1, 3 * most)   # needless, the last least so
    chosen = torch.nonzero(tr.cfg.density.needless(tr)).squeeze(1)
    assert most >= 2 and torch.equal(chosen, torch.arange(2 * most, 3 * most))


def test_a_clone_under_significance_renders_as_its_original_did(small_scene):
    """With significance on, a clone and its original share the original's opacity and shrink
    (3DGS-MCMC's split): the pair renders nearly as the original did, where INRIA's copy (the
    same opacity twice) darkens or brightens the spot."""
    from recgs_addon.core.render.rasterizer import render
    from recgs_addon.core.train.data import view_tensors

    def change(keeps: bool) -> float:
        tr = make_trainer(small_scene, tiny_cfg(prune_weight=0.25, clone_keeps_render=keeps))
        cam, _ = tr.data.view(tr.data.train_ids[0], 1)
        viewmat, K = view_tensors(cam, tr.device)

        def image():
            p = tr.params
            with torch.no_grad():
                return render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], tr._sh(), viewmat,
                              K, cam.width, cam.height, sh_degree=tr.sh_degree, compiled=False).rgb

        s = tr.stats
        s.count[:] = 5
        s.peak_weight[:] = 10.0
        s.accum[:] = 0.0
        s.accum[:40] = 1.0 * s.count[:40]
        with torch.no_grad():
            tr.params["log_scales"][:40] = float(np.log(2e-3 * tr.extent))
            tr.params["logit_opacities"][:40] = 1.0
        before = image()
        info = tr.densify()
        assert info["cloned"] == 40 and info["split"] == 0
        return float((image() - before).abs().sum())

    keeps, copies = change(True), change(False)
    assert copies > 0.5 and keeps < copies / 3   # the split keeps the peak and the integral, not the profile


def test_a_job_whose_finishing_would_not_fit_its_limit_trains_smaller(small_scene, tmp_path, capsys, monkeypatch):
    """Where the outputs and scores alone (the renders and writes after training, which go
    with the pixels) would take more than FINISH_SHARE of the time limit at the training size,
    the job trains at a half or a quarter of the long side and says so first; where that fits
    already, where no limit is set or no smaller size is allowed, the size is kept."""
    from types import SimpleNamespace

    from recgs_addon.cli import main
    from recgs_addon.commands import train as train_cmd
    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.train.progress import FINISH_SHARE, ProgressMixin

    # the finishing, in seconds, as a tenth of the training width: 4 s at 40 px, 1 s at 20 px
    monkeypatch.setattr(ProgressMixin, "finishing_estimate", lambda self: 0.1 * self.data.sizes[0][0])
    monkeypatch.setattr(train_cmd, "MIN_FIT_SIDE", 16)
    out = tmp_path / "out"
    code = main(["train", str(small_scene), "--out", str(out), "--eager", "--max-minutes", "0.05", "--holdout-every", "4"])
    err = capsys.readouterr().err
    assert code == 0, err
    m = json.loads((out / "metrics.json").read_text())
    fitted = m["plan"]["fitted"]
    assert fitted["from"] == [40, 30] and fitted["to"] == [20, 15] and m["plan"]["width"] == 20, fitted
    assert "size: at 40x30 the outputs and scores alone would take about 4 s of the 3-s limit: training at 20x15" in err
    assert read_image(next((out / "renders").glob("*.png"))).shape[:2] == (15, 20)

    monkeypatch.undo()   # MIN_FIT_SIDE as it is

    def stub(finish, side=1000, limit=100.0):
        return SimpleNamespace(time_limit_s=limit, finishing_estimate=lambda: finish, render_output=lambda i: None,
                               data=SimpleNamespace(test_ids=[1], train_ids=[0], sizes=[(side, side // 2)] * 2))

    share = FINISH_SHARE * 100.0
    assert train_cmd._fitting_side(stub(share)) is None                       # fits as it is
    assert train_cmd._fitting_side(stub(10 * share, limit=None)) is None      # no limit
    assert train_cmd._fitting_side(stub(3 * share))["side"] == 500            # a half is enough
    assert train_cmd._fitting_side(stub(10 * share, side=2000))["side"] == 500   # a quarter, the least
    assert train_cmd._fitting_side(stub(100 * share, side=2000))["side"] == 500
    assert train_cmd._fitting_side(stub(10 * share))["side"] == 500           # no smaller than MIN_FIT_SIDE
    assert train_cmd._fitting_side(stub(10 * share, side=600)) is None
    assert train_cmd._fitting_side(stub(10 * share, side=30)) is None


def test_the_finishing_counts_its_small_renders_by_their_pixels():
    """The views per Gaussian and the coverage render every training view at most 400 px on the
    long side: counted by their share of the pixels, no less than SMALL_RENDER_FLOOR of a render
    at the training size (what a render does per Gaussian stays)."""
    from recgs_addon.commands.train import SMALL_RENDER_FLOOR, small_render_share

    assert small_render_share([(320, 240)]) == 1.0                   # no smaller than the training size
    assert small_render_share([(686, 367), (600, 300)]) == 0.25       # half the side: a quarter
    assert small_render_share([(1371, 733)]) == SMALL_RENDER_FLOOR    # 1/16 of the pixels, the floor
