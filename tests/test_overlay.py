"""Burned-in overlays (core/train/overlay.py): pixels that stay put while the scene moves are
found, grown over a time stamp's changing digits, and left out of the loss, the scores and the
light finding; a scene at rest or without an overlay masks nothing."""
import shutil

import numpy as np
import pytest
import torch

from conftest import write_rendered_scene
from recgs_addon.core.train import overlay as ov


def _frames(n=20, stamp=True, moving=True, seed=0):
    """Grey frames of a textured seabed sliding by, with a time stamp (steady digits and a
    changing one) burned into the top-left corner."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.2, 0.8, (120, 1000))
    base = (base + np.roll(base, 1, 0) + np.roll(base, 1, 1)) / 3
    out = []
    for t in range(n):
        f = base[:, (3 * t if moving else 0):][:, :400].copy()[:90]
        if stamp:
            f[4:10, 6:40] = 0.1
            f[5:9, 8:38:3] = 1.0                       # steady digits
            f[5:9, 42:46] = 1.0 if t % 2 else 0.1      # the seconds: change every frame
        out.append(torch.tensor(f, dtype=torch.float32))
    return out


def test_a_time_stamp_is_found_with_its_changing_digits():
    found = ov.find_overlay(_frames())
    assert found.mask is not None and 0 < found.share < 0.1, found.reason
    assert bool(found.mask[5:9, 8:46].all())           # the steady digits and the changing one
    assert not bool(found.mask[40:, 60:].any())        # the seabed counts
    keep = ov.mask_at(found, 180, 800)                 # at another size
    assert not bool(keep[10:18, 16:92].any()) and bool(keep[80:, 120:].all())


def test_no_overlay_and_a_scene_at_rest_mask_nothing():
    assert ov.find_overlay(_frames(stamp=False)).mask is None
    still = ov.find_overlay(_frames(moving=False))
    assert still.mask is None and "hardly change" in still.reason
    assert ov.find_overlay(_frames(n=2)).mask is None


@pytest.fixture(scope="module")
def stamped_scene(tmp_path_factory):
    """The bundled sample survey with a time stamp burned into every photo's top-left corner."""
    from conftest import ROOT
    from recgs_addon.core.io.images import read_image, write_image

    root = tmp_path_factory.mktemp("stamp") / "sample"
    shutil.copytree(ROOT / "data" / "sample", root)
    for p in sorted((root / "images").iterdir()):
        img = read_image(p)
        img[3:12, 4:60] = 0.05
        img[5:10, 6:58:4] = 1.0
        write_image(p, img)
    return root


def test_the_overlay_counts_nowhere(stamped_scene):
    """Found on the survey, the overlay weighs nothing in the loss and the scores: a render
    that paints anything there scores the same."""
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer
    from recgs_addon.core.train.losses import psnr

    tr = make_trainer(stamped_scene, preset("default", iterations=1, compiled=False, holdout_every=4))
    found = tr.data.overlay()
    assert found.mask is not None, found.reason
    i = tr.data.test_ids[0]
    keep = tr.counts(i)
    assert keep is not None and not bool(keep[3:12, 4:60].any()) and float(keep.float().mean()) > 0.8
    photo = tr.data.view(i, 1)[1]
    a, b = photo.clone(), photo.clone()
    a[3:12, 4:60], b[3:12, 4:60] = 0.0, 0.5
    assert psnr(a, photo, keep) == psnr(b, photo, keep) == float("inf")
    assert psnr(a, photo) != psnr(b, photo)
    # the loss: the overlay's pixels carry no weight, not even through the SSIM windows that
    # reach into it from outside
    j = tr.data.train_ids[0]
    _, out, loss = tr._forward(j, 1, False)
    grad = torch.autograd.grad(loss, out.rgb)[0].abs()
    hidden = ~tr.counts(j)
    assert bool(hidden[3:12, 4:60].all())
    assert float(grad[hidden].max()) == 0.0 and float(grad[~hidden].max()) > 0.0


def test_a_survey_without_an_overlay_masks_nothing():
    from conftest import ROOT
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import load_data

    data = load_data(ROOT / "data" / "sample", preset("default"))
    assert data.overlay().mask is None and data.valid(0, 192, 256) is None
