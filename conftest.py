"""Root pytest configuration: the notebooks (collected by nbmake) run in their quick mode, in the
slow tier.

Each notebook reads ``OMNISCAPE_NB_QUICK``; under pytest it is set to "1" here (unless already
set), so CI trains and renders for a few steps only. The outputs committed in ``notebooks/``
come from full runs, from the ``notebooks/`` folder: ``OMNISCAPE_NB_QUICK=0
../.venv/bin/jupyter execute --inplace --timeout=-1 NAME.ipynb``.

A notebook takes 20-60 s even in its quick mode, so each is marked ``slow``: ``pytest -m slow``
runs them (tests/README.md, "Tiers").
"""

import os

import pytest

os.environ.setdefault("OMNISCAPE_NB_QUICK", "1")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.slow)
