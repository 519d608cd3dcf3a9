"""Caustic estimators kept for the record's comparisons (benchmarks/RESULTS.md), beside the two a
run uses (the paper's low-pass and the passes, ``recgs_addon/core/caustics``): the multi-view
consensus (``consensus.py``), per-view light fields (``lightfield.py``) and the survey's gain
likelihood (``likelihood.py``), each run as RecGS with its own estimates (``methods.py``).

``python -m benchmarks.caustic_estimators train SURVEY --out OUT --mode recgs --estimator NAME``
is the train command with them added (``__main__.py``).
"""
