"""``python -m recgs_addon``: the command-line entry point (see ``recgs_addon.cli``)."""
import os
import sys

# The worker's threads sleep while they wait for work instead of spinning (OpenMP's passive
# wait; read once, when torch loads its OpenMP runtime, so before anything imports torch). On a
# machine that runs anything else beside the job (Blender, a second job, numba's compile in the
# background) spinning threads burn the time slices of the threads they wait for: beside a
# second job a job's start (many small steps) took ten to twenty times as long and its training
# steps twice, against a few per cent at most alone (benchmarks/RESULTS.md#threads-wait-passive).
# A policy the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cli import main  # noqa: E402

sys.exit(main())
