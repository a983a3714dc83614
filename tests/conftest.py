"""Shared fixtures: small generated takes with ground truth (seeded)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapskel.synth.chains import hang_chain, kirk_linkage

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
SAMPLE_DATA = REPO / "sample_data"


@pytest.fixture(scope="session")
def linkage():
    """Kirk's linkage, 0.5 mm noise, 20 s at 120 Hz."""
    return kirk_linkage(2400, rng=np.random.default_rng(7), noise_mm=0.5)


@pytest.fixture(scope="session")
def chain433():
    return hang_chain((4, 3, 3), 300, rng=np.random.default_rng(3), link_length=300.0)
