"""Speed against accuracy of every rendering setting and its peers: ``omniscape-torch bench``.

A thin wrapper: the runner lives in the package (``omniscape_torch/benchmark.py``, where the rows,
the references and the outputs are documented), so that ``omniscape-torch bench`` works from an
installed package too. This script runs the checkout it lives in.

Usage::

    python benchmarks/run.py             # 1024 x 1024 from 6 x 512, 2 threads (< 10 min)
    python benchmarks/run.py --quick     # 256 x 256 from 6 x 128 (about a minute)
    python benchmarks/run.py --device auto

Outputs: ``benchmarks/results/bench.json``, ``bench.png`` and ``bench.md`` (``--out-dir``).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Benchmark the checkout this script lives in, not whatever copy is installed.
sys.path.insert(0, str(ROOT))

from omniscape_torch.benchmark import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(out_dir=ROOT / "benchmarks" / "results"))
