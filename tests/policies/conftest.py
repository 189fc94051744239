import pytest

from tests.policies.openvla_tiny import make_policy


@pytest.fixture(scope="module")
def policy():
    """One tiny OpenVLA a test module shares (drawn from seed 0)."""
    return make_policy()
