"""The train command with the estimators kept for comparisons added to ``--estimator``
(``consensus``, ``lightfield``, ``likelihood``) and their settings::

    python -m benchmarks.caustic_estimators train SURVEY --out OUT --mode recgs --estimator lightfield \\
        [--lf-lambda 0.05] [--lf-tau 0.02] [--light-sigma 1] [--consensus-stat mean] [--consensus-q 0.25]

Run from the repository's root, in the project's environment. The other options are the train
command's (``python -m recgs_addon train --help``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv: Optional[list] = None) -> int:
    from benchmarks.caustic_estimators.consensus import STATS
    from benchmarks.caustic_estimators.methods import (METHODS, ConsensusRecGS, LightFieldRecGS, LikelihoodRecGS,
                                                       register)
    from recgs_addon.cli import COMMANDS, build_parser

    own = argparse.ArgumentParser(add_help=False)
    own.add_argument("--lf-lambda", type=float, default=LightFieldRecGS.lam, help="lightfield: TV weight")
    own.add_argument("--lf-tau", type=float, default=LightFieldRecGS.tau, help="lightfield: dead band (log light)")
    own.add_argument("--light-sigma", type=float, default=LikelihoodRecGS.sigma,
                     help="likelihood: the light's blur in pixels at 320 px wide")
    own.add_argument("--consensus-stat", choices=STATS, default=ConsensusRecGS.stat,
                     help="consensus: the per-pixel statistic over the views that see it")
    own.add_argument("--consensus-q", type=float, default=ConsensusRecGS.q, help="consensus: the quantile")
    mine, rest = own.parse_known_args(sys.argv[1:] if argv is None else argv)
    LightFieldRecGS.lam, LightFieldRecGS.tau = mine.lf_lambda, mine.lf_tau
    LikelihoodRecGS.sigma = mine.light_sigma
    ConsensusRecGS.stat, ConsensusRecGS.q = mine.consensus_stat, mine.consensus_q
    register()
    parser = build_parser()
    for action in parser._actions:   # the train command's --estimator takes the added names too
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices["train"]._actions:
                if sub.dest == "estimator":
                    sub.choices = tuple(sub.choices) + tuple(METHODS)
    args = parser.parse_args(rest)
    return COMMANDS[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
