from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# shared/ sits beside the checkout (locally and in CI); the lab files are also shipped
# with the package so that tests run from an installed wheel too.
LAB_CANDIDATES = [REPO.parent / "shared" / "data" / "ais_lab20", REPO / "edge_clients" / "data" / "ais_lab20"]


@pytest.fixture(scope="session")
def lab_dir() -> Path:
    for p in LAB_CANDIDATES:
        if (p / "intrinsics.yaml").is_file():
            return p
    pytest.fail("the 20-camera lab (shared/data/ais_lab20) is not beside the checkout")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Everything in tests/integration is ``serial``: real services fed by sensors in real
    time, whose tests a second worker's load would turn into races (.ci/run)."""
    integration = REPO / "tests" / "integration"
    for item in items:
        if integration in item.path.parents:
            item.add_marker(pytest.mark.serial)
