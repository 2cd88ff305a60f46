"""Cable lengths as measurement data: synthetic tables, joint states from them, bad-data errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax.modules import (
    arm_cable_lengths,
    arm_states_from_cable_lengths,
    cable_length_columns,
    cable_length_table,
    check_cable_lengths,
    module_states_from_cable_lengths,
    sample_feasible_states,
    simulate_cable_lengths,
)

M = 40  # the sampler batch of the other module tests (shared compilation)
ROWS = [f"line {i + 4} (pose p{i})" for i in range(M)]


@pytest.fixture(scope="module")
def data(cdra):
    q = jax.jit(sample_feasible_states, static_argnums=2)(jax.random.PRNGKey(5), cdra, M)
    exact = {k: np.asarray(v) for k, v in jax.jit(arm_cable_lengths)(cdra, q).items()}
    return np.asarray(q), exact


def _copy(lengths):
    return {k: np.array(v) for k, v in lengths.items()}


def test_columns_and_table(cdra, data):
    q, exact = data
    cols = cable_length_columns(cdra)
    assert cols["elbow"] == ("elbow.l1", "elbow.l2")
    assert list(cols) == ["shoulder", "elbow", "wrist"]
    names, values = cable_length_table(exact, cdra)
    assert names == [c for m in cols.values() for c in m]
    assert values.shape == (M, 12)
    np.testing.assert_array_equal(values[:, 6:8], exact["elbow"])
    with pytest.raises(ValueError, match=r"lengths\['wrist'\] must be \(m, 4\)"):
        cable_length_table({"wrist": exact["wrist"][:, :3]}, cdra)
    with pytest.raises(ValueError, match="no modules \\['hand'\\]"):
        cable_length_table({"hand": exact["wrist"]}, cdra)


def test_states_from_exact_and_noisy_lengths(cdra, data):
    q, exact = data
    np.testing.assert_allclose(arm_states_from_cable_lengths(cdra, exact), q, atol=1e-9)
    noisy = jax.jit(simulate_cable_lengths)(jax.random.PRNGKey(0), cdra, jnp.asarray(q), 0.01)
    diff = np.concatenate([np.asarray(noisy[k]) - exact[k] for k in exact], axis=1)
    assert 0.005 < diff.std() < 0.02
    got = arm_states_from_cable_lengths(cdra, noisy)
    assert np.abs(got - q).max() < 5e-3
    # mixing cable lengths and joint coordinates, module by module
    states = cdra.split_state(jnp.asarray(q))
    mixed = arm_states_from_cable_lengths(
        cdra, {"shoulder": exact["shoulder"]}, {"elbow": states[1], "wrist": states[2]}
    )
    np.testing.assert_allclose(mixed, q, atol=1e-9)
    with pytest.raises(ValueError, match=r"no state for modules \['wrist'\]"):
        arm_states_from_cable_lengths(cdra, {"shoulder": exact["shoulder"]}, {"elbow": states[1]})
    with pytest.raises(ValueError, match=r"both as cable lengths and as joint states"):
        arm_states_from_cable_lengths(cdra, exact, {"elbow": states[1]})


@pytest.mark.parametrize(
    ("module", "row", "col", "value", "message"),
    [
        ("shoulder", 3, 2, -2.5, r"line 7 \(pose p3\), column shoulder\.l3: cable length -2\.5 mm"),
        ("wrist", 0, 3, np.nan, r"line 4 \(pose p0\), column wrist\.l4: cable length is nan"),
        ("elbow", 5, 1, np.inf, r"line 9 \(pose p5\), column elbow\.l2: cable length is inf"),
        ("shoulder", 8, 4, 0.0, r"line 12 \(pose p8\), column shoulder\.l5: cable length 0 mm"),
        ("shoulder", 10, 0, "+4", r"line 14 \(pose p10\), column shoulder\.l1: no pose of module"),
        ("shoulder", 7, 5, "-3", r"line 11 \(pose p7\), column shoulder\.l6: no pose of module"),
        ("elbow", 2, 0, "+3", r"line 6 \(pose p2\), columns elbow\.l1, elbow\.l2: no pose of"),
    ],
)
def test_bad_cable_data_names_the_row_and_the_column(cdra, data, module, row, col, value, message):
    _, exact = data
    bad = _copy(exact)
    if isinstance(value, str):
        bad[module][row, col] += float(value)  # lengths that no pose can produce
    else:
        bad[module][row, col] = value
    with pytest.raises(ValueError, match="^meas.csv: " + message):
        arm_states_from_cable_lengths(cdra, bad, rows=ROWS, source="meas.csv")


def test_wrong_column_count_and_impossible_rows_are_all_diagnosed(cdra, data):
    _, exact = data
    wrist = cdra.module("wrist")
    with pytest.raises(
        ValueError, match=r"meas.csv: columns wrist.l1, wrist.l2, wrist.l3: .*4 cables"
    ):
        module_states_from_cable_lengths(
            wrist,
            exact["wrist"][:, :3],
            source="meas.csv",
            columns=["wrist.l1", "wrist.l2", "wrist.l3"],
        )
    bad = np.array(exact["wrist"])
    bad[[1, 6], 2] += 6.0
    states, rms, problems = check_cable_lengths(wrist, bad)
    # one redundant cable: the rows are found, no single column is blamed
    assert [(p.row, p.column) for p in problems] == [(1, None), (6, None)]
    assert "cannot be pinned to one column" in problems[0].message
    assert np.isnan(states[[1, 6]]).all() and not np.isnan(np.delete(states, [1, 6], 0)).any()
    assert rms[1] > 0.1 and rms[6] > 0.1 and np.delete(rms, [1, 6]).max() < 1e-9
    # the tolerance is the caller's: a 0.05 mm misfit passes the default 0.1 mm, not 0.01 mm
    small = np.array(exact["wrist"])
    small[4, 0] += 0.2
    assert check_cable_lengths(wrist, small)[2] == []
    with pytest.raises(
        ValueError, match="row 5, columns wrist.l1, .*: no pose .* tolerance 0.01 mm"
    ):
        module_states_from_cable_lengths(wrist, small, residual_tol=0.01)
