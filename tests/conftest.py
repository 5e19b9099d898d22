from __future__ import annotations

import pytest

from tests.rig import Rig


@pytest.fixture
def rig() -> Rig:
    return Rig()


@pytest.fixture
def ready_rig() -> Rig:
    return Rig().ready()
