"""RecGS's caustic estimates: each training view's C (the maps) and the caustic-free image a
view fits, and what a held-out render is scored against.

:class:`Estimates` is a part of :class:`.recgs.RecGS` (its state lives there). It makes the
estimates of the two estimators a run uses: the low-pass estimate of the paper
(``estimate.py``), and the targets from the passes that saw each point (``passes.py``, with the
survey's geometry from ``geometry.py`` and the look frames of ``core/io/looks.py``).
:func:`choose_estimator` is what ``auto`` stands for on a survey. An estimator kept for the
record's comparisons subclasses :class:`.recgs.RecGS` where the benchmarks keep it
(``config.register_estimator``) and replaces the hooks it needs: ``_estimate`` and
``_decaustic`` (one view's C and its caustic-free photo), ``_maps_from`` (a round's maps from
the renders), ``_scored_against`` (a held-out photo's reference once C is in use) and
``_by_view`` (whether a view's C comes from its own photo and render alone).
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np
import torch

from ..io.frames import read_frame_times
from ..io.looks import MAX_BRACKET_S, look_reader, place_looks, read_looks
from ..model.colour import linear_to_srgb, lit_by, srgb_to_linear
from ..model.lamp import Lamp
from ..train.data import view_tensors
from ..train.lamp import centre_range
from . import fft_filter, geometry, passes
from .estimate import compensate_caustics, estimate_caustics, remove_caustics
from .light import CAMERA_FLOOR
from .robust import trim_weights

#: auto: the survey's median independent passes over a seabed point (sparse points, before
#: training; frames under a second apart count once, core/train/coverage.py) from which the
#: targets come from the passes (``passes.py``); below it, the paper's low-pass estimate. With
#: two passes a point the floor of the light is seen at most points; where fewer passes saw a
#: pixel the pass estimator keeps the low-pass target itself (benchmarks/RESULTS.md).
PASSES_MIN = 2


#: passes: a training view whose target comes from the passes on at least this share of its
#: pixels does not follow the model: its estimate is made once, and later rounds and the final
#: outputs keep it (the low-pass target on the rest, against the model of that round) instead of
#: rendering the view again.
MODEL_FREE_SHARE = 0.99

#: passes: the moving light's standard deviation between frames (log units, benchmarks/RESULTS.md:
#: 0.006 on a survey without caustics, from misregistered texture; 0.37 under light networks)
#: below which there are no caustics to remove.
LIGHT_FLOOR = 0.03
#: A look frame is gathered from where it lines up with its nearest keyframe at least this share
#: as well as keyframes next in time line up with each other (their median over up to
#: LOOK_REFERENCE_PAIRS pairs; ``Estimates._aligned_looks``).
LOOK_ALIGNMENT = 0.8
LOOK_REFERENCE_PAIRS = 16


def choose_estimator(data) -> tuple[str, str]:
    """The estimator ``auto`` stands for on this survey, and why: the passes where the survey's
    sparse points show each seabed point seen in enough independent passes, the low-pass
    estimate otherwise."""
    from ..train.coverage import sparse_coverage

    cov = sparse_coverage(data)
    if not cov.points:
        return "lowpass", "no sparse points to count views with"
    views = f"a median of {cov.median_views:g} training views in {cov.median_passes:g} passes a seabed point"
    if cov.median_passes >= PASSES_MIN:
        return "passes", f"{views}: targets from the passes that saw each point (>= {PASSES_MIN} passes)"
    return "lowpass", f"{views}: the low-pass estimate (the passes need >= {PASSES_MIN})"


class Estimates:
    """The estimator side of :class:`.recgs.RecGS` (module docstring)."""

    def _reference(self, index: int, image: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
        """What a held-out render is scored against for the trainer's decisions: the photo
        during the warm-up (it is plain 3DGS and decides as plain 3DGS does: scored against
        compensated photos, growth went on to 3x the Gaussians, half of them carrying no
        view), the photo with its caustics compensated once C is in use."""
        if self.stage == "warmup" or self.dropped:   # plain 3DGS decides as plain 3DGS
            return image
        if self.references is not None and index in self.references:
            return self.references[index].float()
        return self._scored_against(image, render)

    def _scored_against(self, image: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
        """A held-out photo with the caustics the estimator sees against ``render`` taken off."""
        return self._decaustic(image, self._estimate(image, render, self._eval_k))

    @property
    def _eval_k(self) -> int:
        """The filter held-out views are compensated with: the training views' (the paper's
        9 until it is chosen)."""
        return self.k or fft_filter.DEFAULT_K

    @property
    def _passes(self) -> bool:
        return self.ccfg.estimator == "passes"

    def _decaustic(self, image: torch.Tensor, cmap: torch.Tensor) -> torch.Tensor:
        """The photo ``image`` with its caustic estimate ``cmap`` taken off."""
        return remove_caustics(image, cmap, self.ccfg.caustic_model)

    def _estimate(self, image: torch.Tensor, rgb: torch.Tensor, k: int) -> torch.Tensor:
        """C of a view from its photo and render (the low-pass estimate, filter size ``k``),
        over the pixels trimming keeps."""
        w = trim_weights(image, rgb, self.targets.k) if self.targets.k else None
        return estimate_caustics(image, rgb, k, self.ccfg.caustic_model, self.ccfg.caustic_dc, w)

    def caustic_map(self, index: int) -> torch.Tensor:
        """Additive caustic estimate ``C = I - (caustic-free I)`` of a training view (full res)."""
        image = self.data.view(index, 1)[1]
        return image - self.decaustic_image(index)

    def takes_light_off(self) -> bool:
        """No light estimated (none yet, or C dropped): every caustic-free photo is the photo."""
        return bool(self.maps)

    @torch.no_grad()
    def decaustic_image(self, index: int) -> torch.Tensor:
        image = self.data.view(index, 1)[1]
        cmap = self.maps.get(index)
        if cmap is not None and self.final and self._by_view and not self._model_free(index):
            # against the model kept
            cmap = self._view_estimate(index, self.trainer.render_view(index))
        return image if cmap is None else self._decaustic(image, cmap.float())

    def _set_maps(self, maps: dict[int, torch.Tensor]) -> None:
        """Use these estimates: each training view now fits its caustic-free image. The maps
        are kept as float16, as the targets are (``FixedTargets``)."""
        self.maps = {i: m.to(torch.float16) for i, m in maps.items()}
        self.targets.clear()
        for i, m in self.maps.items():   # from the kept maps, so a resumed run sets the same targets
            self.targets.put(i, self._decaustic(self.data.view(i, 1)[1], m.float()))

    # --- one round's estimates ----------------------------------------------------------
    def _estimates(self, ids: list[int]) -> dict[int, torch.Tensor]:
        """Every training view's new estimate of C (the estimator's maps) against the model now."""
        if self._passes and self.geometry is None:   # the first round, or the first after a resume
            self.geometry = self._make_pass_estimates()
        if self._passes and self.geometry.get("overrun"):   # given up: the round drops C
            return {}
        kept = {i: self.maps[i].float() for i in ids if self._model_free(i)}
        renders = {i: self.trainer.render_view(i) for i in ids if i not in kept}
        if self.k is None:
            self.k = fft_filter.choose_k([self.data.view(i, 1)[1] - renders[i] for i in ids])
        return self._maps_from(ids, kept, renders)

    def _maps_from(self, ids: list[int], kept: dict[int, torch.Tensor],
                   renders: dict[int, torch.Tensor]) -> dict[int, torch.Tensor]:
        """A round's maps of views ``ids``: those ``kept`` as they are (they do not follow the
        model), every other view's from its render."""
        return {**kept, **{i: self._view_estimate(i, renders[i]) for i in renders}}

    def _model_free(self, index: int) -> bool:
        """passes: training view ``index``'s estimate does not follow the model (its pixels come
        from the passes, :data:`MODEL_FREE_SHARE`), and one is made."""
        g = self.geometry
        return bool(self._passes and g is not None and g.get("shares") and index in self.maps
                    and g["shares"].get(index, 0.0) >= MODEL_FREE_SHARE)

    @property
    def _by_view(self) -> bool:
        """The estimator makes a view's C from that view's photo and render alone (one that needs
        every view at once remakes the maps against the model kept at the end)."""
        return True

    def _view_estimate(self, index: int, render: torch.Tensor) -> torch.Tensor:
        """C of training view ``index`` against ``render`` (``_by_view`` estimators): the
        low-pass estimate, or (passes) the photo less its target: the passes' estimate where
        enough passes saw a pixel, the low-pass target elsewhere."""
        photo = self.data.view(index, 1)[1]
        if not self._passes:
            return self._estimate(photo, render, self.k)
        if self.geometry is None:   # the first round, or the first use after a resume (not checkpointed)
            self.geometry = self._make_pass_estimates()
        g = self.geometry
        if g["estimates"] is None:   # no moving light: the round that finds it drops C
            return self._estimate(photo, render, self.k)
        low = compensate_caustics(photo, render, self.k, "additive", self.ccfg.caustic_dc)
        return photo - passes.blend(g["estimates"][index].float(), g["weights"][index].float(), low)

    def _make_pass_estimates(self) -> dict:
        """The passes' part of the targets (``passes.py``), which does not depend on the model:
        every training and held-out frame with the survey's geometry (sparse points refined by
        a plane sweep; the model's depth where there are no points), the light's statistics,
        each training frame's estimate and weight (kept as float16), and the held-out frames'
        references gathered from the training frames alone."""
        t = time.perf_counter()
        tr, data = self.trainer, self.data
        deadline = getattr(self, "pass_deadline", None)
        limit = tr.time_limit_s
        if deadline is not None and limit is not None:
            # what the limit has left now, less the finishing and training's own share: a slow
            # start (a cold compiler cache, a busy machine) leaves the work less than its plan
            left = limit - tr.elapsed - tr.finishing_reserve() - MIN_TRAINING_AFTER * limit
            planned = getattr(self, "planned_seconds", 0.0)
            if left < planned:
                why = (f"the caustic work (about {planned:.0f} s) would leave training less than "
                       f"{100 * MIN_TRAINING_AFTER:.0f} % of the {limit:.0f}-s limit after {tr.elapsed:.0f} s of work "
                       "before it: trained as plain 3DGS")
                self.pass_info = {"seconds": 0.0, "overrun": why}
                return {"estimates": None, "light": {"light_std": None}, "overrun": why}
            deadline = min(deadline, left)

        def check() -> None:   # the work given up where it runs past its share of the time limit
            if deadline is not None and time.perf_counter() - t > deadline:
                raise _Overrun(f"the caustic work ran past {deadline:.0f} s, its share of the time limit "
                               f"({time.perf_counter() - t:.0f} s, planned {getattr(self, 'planned_seconds', 0):.0f}): "
                               "trained as plain 3DGS")
        try:
            return self._pass_estimates(t, check)
        except _Overrun as why:
            self.pass_info = {"seconds": round(time.perf_counter() - t, 2), "overrun": str(why)}
            return {"estimates": None, "light": {"light_std": None}, "overrun": str(why)}

    def _pass_estimates(self, t: float, check) -> dict:
        """:meth:`_make_pass_estimates`' work, begun at ``t`` (``perf_counter``), ``check()``
        called between frames."""
        tr, data = self.trainer, self.data
        ids = sorted(data.train_ids + data.test_ids)
        times = read_frame_times(data.scene.scene_dir) or {}
        scale = getattr(self, "pass_scale", 1)   # the frames at 1 / scale of the training size
        views = []
        for i in ids:
            cam, photo = data.view(i, scale)
            viewmat, K = view_tensors(cam, tr.device)
            out = tr.render_output(i, level=scale)
            covered = out.alpha > 0.5
            keep = tr.counts(i, scale)   # a burned-in overlay is no seabed
            views.append(geometry.PassView(photo, out.depth / out.alpha.clamp_min(1e-6),
                                           covered if keep is None else covered & keep, viewmat, K, times.get(cam.name)))
        pts = torch.as_tensor(data.scene.points, dtype=torch.float32, device=tr.device)
        brought = geometry.prior_geometry(views, pts)
        lit = self._even_the_light(views, ids, scale)
        overlap = geometry.overlap_matrix(views)
        pos = {i: n for n, i in enumerate(ids)}
        train, test = [pos[i] for i in data.train_ids], [pos[i] for i in data.test_ids]
        # the light first (a few seconds): without moving light C is dropped, so the plane
        # sweep and the gathers (most of the time) are not made
        water = tr.medium.values() if tr.medium is not None else None
        parts = {"setup": time.perf_counter() - t}
        light = passes.light_statistics(views, overlap, train, water=water)
        parts["light"] = time.perf_counter() - t - sum(parts.values())
        if light["light_std"] is not None and light["light_std"] < LIGHT_FLOOR:
            self.pass_info = {"seconds": round(time.perf_counter() - t, 2),
                              "part_seconds": {k: round(v, 2) for k, v in parts.items()},
                              **{k: v for k, v in light.items() if k != "correlation_s"}}
            return {"estimates": None, "light": light}
        geometry.refine_geometry(views, overlap, brought, pts, check=check)
        # where the depth is ambiguous (repetitive texture, grazing views) the passes abstain:
        # those pixels are neither gathered nor gathered from, and keep their low-pass target
        abstained = []
        for v in views:
            if v.ambiguous is not None:
                abstained.append(float((v.ambiguous & v.covered).sum()) / max(1, int(v.covered.sum())))
                v.covered = v.covered & ~v.ambiguous
        parts["geometry"] = time.perf_counter() - t - sum(parts.values())
        settings = passes.settings_for(light, statistic=self.ccfg.pass_statistic, min_passes=self.ccfg.pass_min)
        # the look frames (a video's frames between the keyframes) are gathered from as the
        # training frames are; they gather nothing themselves
        looks, look_info = self._look_views(views, ids, scale, pts, check, light)
        frames, sources, wide = views, train, overlap
        if looks:
            n = len(views)
            wide = geometry.with_looks_overlap(overlap, views, looks, train)
            frames, sources = views + looks, train + list(range(n, n + len(looks)))
            settings = passes.with_looks(settings, [v.time for v in frames])
        parts["looks"] = time.perf_counter() - t - sum(parts.values())
        # with the water modelled, the frames' colours are compared at each frame's own range
        est, wts, info = passes.pass_estimates(frames, settings, ids=train, overlap=wide, sources=sources, water=water,
                                               check=check, keyframes=set(train) if looks else None)
        est = [self._lift(_relit(e, lit, k), i, scale) for e, k, i in zip(est, train, data.train_ids)]
        wts = [_resize(w, *data.sizes[i][::-1]) for w, i in zip(wts, data.train_ids)]
        parts["targets"] = time.perf_counter() - t - sum(parts.values())
        if test:
            refs, _ = passes.pass_targets(views, settings, ids=test, overlap=overlap, sources=train, gains=info["gains"],
                                          water=water, check=check)
            refs = [self._lift(_relit(r, lit, k), i, scale) for r, k, i in zip(refs, test, data.test_ids)]
            self.references = {i: r.half() for i, r in zip(data.test_ids, refs)}
            tr.best_by = "psnr"   # the references do not follow the model
        seconds = round(time.perf_counter() - t, 2)
        parts["references"] = seconds - sum(parts.values())
        self.pass_info = {"median_passes": float(np.median(info["passes"])), "share": round(float(np.mean(info["share"])), 4),
                          "scale": scale, "abstained": round(float(np.mean(abstained)), 4) if abstained else 0.0,
                          "part_seconds": {k: round(v, 2) for k, v in parts.items()},
                          "median_looks": round(float(np.median(info["looks"])), 2), "statistic": settings.statistic,
                          **({"look_frames": {**look_info, **({"median_looks_keyframes": round(float(np.median(
                              info["looks_keyframes"])), 2)} if info.get("looks_keyframes") else {})}}
                             if look_info else {}),
                          "pass_seconds": settings.pass_seconds, "seconds": seconds,
                          **{k: v for k, v in light.items() if k != "correlation_s"},
                          "share_per_frame": {data.scene.cameras[i].name: round(float(x), 3)
                                              for i, x in zip(data.train_ids, info["share"])}}
        return {"estimates": {i: e.half() for i, e in zip(data.train_ids, est)},
                "weights": {i: w.half() for i, w in zip(data.train_ids, wts)}, "light": light,
                "shares": dict(zip(data.train_ids, info["share"]))}

    def _lift(self, estimate: torch.Tensor, index: int, scale: int) -> torch.Tensor:
        """A frame's caustic-free estimate made at 1 / ``scale`` of its training size, brought to
        that size: the light it takes off (its ratio to the photo at that size, in linear light)
        put on the full-size photo. The light is smooth beside the texture (caustic cells span
        tens of pixels), so the photo keeps its own detail."""
        if scale == 1:
            return estimate
        small = srgb_to_linear(self.data.view(index, scale)[1].clamp(0, 1))
        ratio = srgb_to_linear(estimate.clamp(0, 1)) / small.clamp_min(1e-3)
        photo = self.data.view(index, 1)[1]
        h, w = photo.shape[:2]
        full = _resize(ratio.clamp(0, 4).permute(2, 0, 1), h, w).permute(1, 2, 0)
        return lit_by(photo, full)

    def _even_the_light(self, views: list, ids: list[int], scale: int = 1) -> Optional[list]:
        """Where the survey shows light fixed to the camera (the trainer's lamp, or the light
        finding's pattern where it varies by :data:`.light.CAMERA_FLOOR` or more), every frame's
        photo is evened by it before frames are compared: a frame's vignetted edge is dark because
        of the lens, not the light on the seabed, and the floor of the light would take it.
        Returns each view's log gain (to light the estimates again), or None."""
        return self._even_photos(views, [self.data.camera(i, scale) for i in ids])

    def _camera_light(self) -> Optional[Lamp]:
        """The light fixed to the camera the frames are evened by (:meth:`_even_the_light`), or None."""
        tr = self.trainer
        lamp = tr.lamp
        light = tr.light or {}
        if lamp is None and light.get("pattern_coef") and light.get("camera", 0.0) >= CAMERA_FLOOR:
            r0 = centre_range(self.data)
            if r0 is not None:
                lamp = Lamp(r0, light["pattern_coef"], *light["range_coef"][:2], device=tr.device)
        return lamp

    def _even_photos(self, views: list, cams: list) -> Optional[list]:
        """Even the photos of ``views`` (cameras ``cams``) by :meth:`_camera_light`; their log gains, or None."""
        lamp = self._camera_light()
        if lamp is None:
            return None
        gains = []
        with torch.no_grad():
            for v, cam in zip(views, cams):
                lg = lamp.log_gain(cam.width, cam.height, cam.cx, cam.cy,
                                   geometry.depth_map(v) * self.trainer.ray_len(cam))
                v.photo = linear_to_srgb((srgb_to_linear(v.photo.clamp(0, 1)) / torch.exp(lg).unsqueeze(-1)).clamp(0, 1))
                gains.append(lg)
        return gains

    def _look_views(self, views: list, ids: list[int], scale: int, points: torch.Tensor,
                    check, light: Optional[dict] = None) -> tuple[list, Optional[dict]]:
        """The survey's look frames (core/io/looks.py) as frames to gather from for the keyframes
        ``views`` (frames ``ids``), at 1 / ``scale`` of the training size: placed (their own pose,
        or between the keyframes before and after), their depth from the survey's sparse points
        and the model, evened as the keyframes are. Frames nearest in time to a held-out keyframe
        are left out (they would carry its light into the training targets). Where the survey's
        ``light`` (``passes.light_statistics``) is shared by keyframes next in time
        (:data:`.passes.SAME_LIGHT`), none are read: the frames between two keyframes saw the
        light those did. Returns (views, what was read, placed and used), or ([], None) where the
        survey has no look frames or they are off."""
        if self.ccfg.looks == "off":
            return [], None
        data, tr = self.data, self.trainer
        found = read_looks(data.scene.scene_dir)
        if found is None:
            return [], None
        t0 = time.perf_counter()
        info: dict = {"listed": found.listed, "missing": len(found.missing), "used": 0}
        shared = (light or {}).get("shared") or {}
        if shared:
            lag = min(shared, key=float)
            if shared[lag] >= passes.SAME_LIGHT:
                info["reason"] = (f"keyframes next in time ({float(lag):g} s apart) share {100 * shared[lag]:.0f} % of "
                                  "their light: the frames between them saw the light they did")
                return [], info
        read = look_reader(data.scene.scene_dir, bool(getattr(data.scene, "undistorted", False)))
        times = read_frame_times(data.scene.scene_dir) or {}
        keys = [data.camera(i, scale) for i in ids]
        placed, counts = place_looks(found.looks, keys, [times.get(c.name) for c in keys])
        info.update(counts)
        test = set(data.test_ids)
        kept = [(lk, cam, k) for lk, cam, k in placed if ids[k] not in test]
        info["near_heldout"] = len(placed) - len(kept)
        most = getattr(self, "max_looks", len(kept))   # as many as fit the caustic work's share of the limit
        if len(kept) > most:
            info["thinned"] = len(kept) - most
            kept = [kept[int(q * len(kept) / most)] for q in range(most)] if most > 0 else []
        out, cams = [], []
        for lk, cam, k in kept:
            check()
            photo = torch.from_numpy(read(lk, cam)).to(tr.device)
            render = tr.render_camera(cam)
            covered = render.alpha > 0.5
            keep = tr.counts(ids[k], scale)   # the nearest keyframe's overlay (the same camera)
            viewmat, K = view_tensors(cam, tr.device)
            out.append(geometry.PassView(photo, render.depth / render.alpha.clamp_min(1e-6),
                                         covered if keep is None else covered & keep, viewmat, K, lk.time))
            cams.append(cam)
        geometry.prior_geometry(out, points)
        self._even_photos(out, cams)
        out, info["misplaced"] = self._aligned_looks(views, out, [k for _, _, k in kept])
        info.update(used=len(out), seconds=round(time.perf_counter() - t0, 2))
        return out, info

    def _aligned_looks(self, views: list, looks: list, near: list[int]) -> tuple[list, int]:
        """The look frames that line up with their nearest keyframe (``near``: its position in
        ``views``) as well as :data:`LOOK_ALIGNMENT` of how keyframes next in time line up with
        each other (:func:`.geometry.alignment`): a frame placed off (interpolated across a
        turn, a jolt of the camera) would show its misregistration as light. Returns (those
        frames, how many were left out)."""
        order = sorted((v.time, k) for k, v in enumerate(views) if v.time is not None)
        pairs = [(a, b) for (ta, a), (tb, b) in zip(order, order[1:]) if tb - ta <= MAX_BRACKET_S]
        step = max(1, len(pairs) // LOOK_REFERENCE_PAIRS)
        ref = [x for x in (geometry.alignment(views[a], views[b]) for a, b in pairs[::step]) if x is not None]
        if not ref:
            return looks, 0
        floor = LOOK_ALIGNMENT * float(np.median(ref))
        kept = [v for v, k in zip(looks, near) if (geometry.alignment(views[k], v) or -1.0) >= floor]
        return kept, len(looks) - len(kept)

def _resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(..., h, w) bilinearly to (..., height, width) (as it is where the size matches)."""
    if tuple(x.shape[-2:]) == (height, width):
        return x
    lead = x.shape[:-2]
    y = torch.nn.functional.interpolate(x.reshape(1, -1, *x.shape[-2:]).float(), size=(height, width),
                                        mode="bilinear", align_corners=False)
    return y.reshape(*lead, height, width).to(x.dtype)


#: The share of a time limit the caustic work leaves to training after it, whatever its plan:
#: the work is not begun where the time left would not allow both, and it is given up where it
#: runs into that share (a two-minute job on a busy machine with a cold compiler cache began its
#: passes 53 s in, ran them 69 s and ended on the warm-up's 100 steps).
MIN_TRAINING_AFTER = 0.15


class _Overrun(Exception):
    """The pass estimator ran past its share of the time limit."""


def _relit(image: torch.Tensor, log_gain: Optional[list], k: int) -> torch.Tensor:
    """An estimate made on evened photos (``Estimates._even_the_light``) lit again as frame ``k`` was."""
    if log_gain is None:
        return image
    return lit_by(image, torch.exp(log_gain[k]).unsqueeze(-1))
