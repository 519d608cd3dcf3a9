"""Caustic removal. The path a run takes, top to bottom:

1. ``light.py``: what light the survey shows, from pairs of frames before training (caustics,
   light fixed to the camera, exposure); ``build.make_method`` looks first and builds the method.
2. ``estimators.py``: what ``auto`` picks (the passes, or the paper's low-pass), and each
   training view's caustic-free target; for the passes it reads the survey's look frames
   (``core/io/looks.py``) beside the keyframes.
3. ``geometry.py`` (with ``warp.py``): where each frame sees the seabed (the sparse points'
   depth refined by a plane sweep) and how much of it the other frames see.
4. ``passes.py`` (with ``tv.py``): the light's statistics, then each frame's light modelled
   against the floor the other passes show, and the colour under it.
5. ``recgs.py``: the recurrent loop (residual, estimate, re-fit on I - C until C settles), its
   do-no-harm tests and the end-of-run choice between the caustic-free and the plain model.

Beside it: ``fft_filter.py`` and ``estimate.py`` (the paper's low-pass estimate), ``robust.py``
(trimming), ``baselines.py`` (the paper's ``filter2d`` and ``joint`` modes), ``cost.py`` (what
the caustic work will cost, for the plan), ``config.py`` (the settings) and ``method.py`` (the
interface every mode has). Estimators kept only for the record's comparisons live with the
benchmarks (``benchmarks/caustic_estimators``)."""
