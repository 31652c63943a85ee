"""Speed against accuracy of every rendering setting and its peers.

A thin wrapper: the runner is ``benchmarks/harness.py`` (where the rows, the references and the
outputs are documented). It runs the checkout this script lives in, not an installed copy.

Usage::

    python benchmarks/run.py             # 1024 x 1024 from 6 x 512, 2 threads (< 10 min)
    python benchmarks/run.py --quick     # 256 x 256 from 6 x 128 (about a minute)
    python benchmarks/run.py --device auto

Outputs: ``benchmarks/results/bench.json``, ``bench.png`` and ``bench.md`` (``--out-dir``);
``--quick`` writes them under ``benchmarks/results/quick/`` (git-ignored), never over the
committed results of a full run.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
# this folder's modules (``harness``, ``common``); ``common`` puts the checkout first
sys.path.insert(0, str(HERE))

from harness import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(out_dir=HERE / "results"))
