"""Training on any torch device: every tensor the eager path makes is made on the model's
device. There is no GPU here, so the check runs on the CPU with torch's default device set
to ``meta``: a tensor made without naming its device lands there, and the first operation
that mixes it with the model's tensors fails, as it would on a GPU (``cuda:0 and cpu``).
Creating constants on the CPU on purpose (a random draw from the trainer's CPU generator, a
filter's taps read as numbers) names ``device="cpu"``."""
import pytest
import torch

from conftest import write_rendered_scene
from recgs_addon.core.caustics.build import make_method
from recgs_addon.core.caustics.config import CausticConfig
from recgs_addon.core.outputs.diagnostics import view_support
from recgs_addon.core.outputs.exports import write_outputs
from recgs_addon.core.train.config import preset


@pytest.fixture(scope="module")
def device_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("device") / "scene"
    write_rendered_scene(root, n_views=8, width=40, height=30, n_gauss=200)
    return root


@pytest.mark.parametrize("mode,strategy,estimator", [
    ("3dgs", "mcmc", "lowpass"), ("3dgs", "adc", "lowpass"), ("recgs", "adc", "lowpass"),
    ("recgs", "adc", "lightfield"), ("recgs", "adc", "consensus"), ("recgs", "adc", "likelihood"),
    ("recgs", "adc", "passes"),
    ("joint", "adc", "lowpass"),
    ("filter2d", "adc", "lowpass"),
])
def test_eager_training_makes_no_tensor_off_the_models_device(device_scene, tmp_path, mode, strategy, estimator):
    from benchmarks.caustic_estimators.methods import register

    register()   # the estimators the benchmarks compare run on the model's device too
    cfg = preset("default", iterations=60, eval_every=20, log_every=20, holdout_every=4, compiled=False,
                 densify_from=10, densify_every=10, densify_until=50, pyramid=((10, 2),), strategy=strategy)
    method = make_method(device_scene, cfg, CausticConfig(mode=mode, warmup=20, recurrence_steps=10, caustics="on",
                                                          estimator=estimator))
    method.trainer.data.load_all(2)
    with torch.device("meta"):
        method.run()
        write_outputs(method, tmp_path)
        view_support(method.trainer)
        method.load_state_dict(method.state_dict())
    assert method.trainer.step >= 40
    if mode == "recgs":
        assert method.recurrence >= 1   # the caustic estimate ran too


def test_the_meta_check_catches_a_tensor_made_on_the_default_device():
    """The check itself: the kind of line that failed on a GPU fails under it."""
    opacity = torch.rand(5)                            # the model's tensors (here: the CPU)
    with torch.device("meta"), pytest.raises(RuntimeError, match="device"):
        scale = torch.ones(5)                          # no device named
        opacity * scale


def test_a_gpu_device_takes_the_eager_path(device_scene):
    from recgs_addon.core.train.compiling import CompileSwitch

    sw = CompileSwitch(None, device="cuda")
    assert sw.compiled() is False and "eager path" in sw.messages[0]
