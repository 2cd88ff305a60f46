import os

# The suite compiles hundreds of small XLA programs that then run for milliseconds, so compile
# time dominates it: build them without LLVM's optimisation passes (about 15-20 % less wall time;
# the arithmetic is the same, XLA's fast-math stays off). Set before JAX starts its backend, and
# inherited by the notebook kernels and the subprocess tests.
# The solvers compile faster still with XLA:CPU's older element-wise emitters, which the package
# uses for its own compilations (cdra_jax.compilation); setting them here gives the tests that
# call jax.jit directly the same configuration. tests/test_compilation.py compares the solvers
# under both emitters explicitly.
for _flag in ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false"):
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def cdra():
    from cdra_jax import default_arm

    return default_arm()


# A UR5-like 6R industrial arm as the same modular chain: six revolute modules about their
# local z axes with the fixed (Denavit-Hartenberg) transforms Tz(d) Tx(a) Rx(alpha) between
# them, lengths in mm. The tool frame is the UR5 flange (DH row 6).
UR5_TOML = """
name = "ur5"
description = "UR5-like 6R arm: DH rows as fixed transforms between revolute modules"

[[frames]]
name = "base"
xyz = [0.0, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link1"
xyz = [0.0, 0.0, 89.159]
rotvec = [1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "link2"
xyz = [-425.0, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link3"
xyz = [-392.25, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link4"
xyz = [0.0, 0.0, 109.15]
rotvec = [1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "link5"
xyz = [0.0, 0.0, 94.65]
rotvec = [-1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "tool"
xyz = [0.0, 0.0, 82.3]
rotvec = [0.0, 0.0, 0.0]
""" + "".join(
    f"""
[[modules]]
name = "joint{i}"
kind = "revolute"
axis = [0.0, 0.0, 1.0]
limits = [[-3.0, 3.0]]
"""
    for i in range(1, 7)
)


@pytest.fixture(scope="session")
def ur5():
    from cdra_jax.io import loads_model

    return loads_model(UR5_TOML, source="<tests/conftest.py UR5_TOML>")


# The longest tests first (each 10-40 s, mostly compilation), so that with `-n 2` the two
# workers end on short tests instead of one of them finishing a notebook alone.
_LONG_FIRST = (
    "tests/test_notebooks.py",
    "tests/test_implicit_derivatives.py",
    "tests/test_diagnosis.py::test_clean_recordings_give_none",
    "tests/test_sweeps.py::test_split_over_two_cpu_devices_matches",
    "tests/test_compilation.py::test_options_change_no_result_of_the_solvers",
    "tests/test_physics.py",
    "tests/test_batching.py::test_solvers_split_over_two_cpu_devices_finish_and_match",
    "tests/test_benchmark_baselines.py",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        for i, prefix in enumerate(_LONG_FIRST):
            if item.nodeid.startswith(prefix):
                return i
        return len(_LONG_FIRST)

    items.sort(key=rank)  # stable: the order within each group is kept
