"""Root pytest configuration: the notebooks (collected by nbmake) run in their quick mode.

Each notebook reads ``OMNISCAPE_NB_QUICK``; under pytest it is set to "1" here (unless already
set), so CI trains and renders for a few steps only. The outputs committed in ``notebooks/``
come from full runs, from the ``notebooks/`` folder: ``OMNISCAPE_NB_QUICK=0
../.venv/bin/jupyter execute --inplace --timeout=-1 NAME.ipynb``.
"""

import os

os.environ.setdefault("OMNISCAPE_NB_QUICK", "1")
