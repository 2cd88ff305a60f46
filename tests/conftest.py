import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def cdra():
    from cdra_jax import default_arm

    return default_arm()
