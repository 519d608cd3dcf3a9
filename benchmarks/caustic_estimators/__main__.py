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

    register()
    parser = build_parser()
    train = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    for action in train._actions:   # --estimator takes the added names too
        if action.dest == "estimator":
            action.choices = tuple(action.choices) + tuple(METHODS)
    added = train.add_argument_group("the estimators the benchmarks compare")
    added.add_argument("--lf-lambda", type=float, default=LightFieldRecGS.lam, help="lightfield: TV weight")
    added.add_argument("--lf-tau", type=float, default=LightFieldRecGS.tau, help="lightfield: dead band (log light)")
    added.add_argument("--light-sigma", type=float, default=LikelihoodRecGS.sigma,
                       help="likelihood: the light's blur in pixels at 320 px wide")
    added.add_argument("--consensus-stat", choices=STATS, default=ConsensusRecGS.stat,
                       help="consensus: the per-pixel statistic over the views that see it")
    added.add_argument("--consensus-q", type=float, default=ConsensusRecGS.q, help="consensus: the quantile")
    args = parser.parse_args(argv)
    if args.command == "train":
        LightFieldRecGS.lam, LightFieldRecGS.tau = args.lf_lambda, args.lf_tau
        LikelihoodRecGS.sigma = args.light_sigma
        ConsensusRecGS.stat, ConsensusRecGS.q = args.consensus_stat, args.consensus_q
    return COMMANDS[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
