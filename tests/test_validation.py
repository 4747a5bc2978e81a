"""The one validation module: every checker's accepted values and its exact messages."""

import pickle

import numpy as np
import pytest

from scg_jax import validation as V
from scg_jax.validation import FieldError


def _reason(check, *args, **kwargs) -> tuple[str, str]:
    with pytest.raises(FieldError) as err:
        check(*args, **kwargs)
    assert isinstance(err.value, ValueError) and str(err.value) == f"{err.value.path}: {err.value.reason}"
    return err.value.path, err.value.reason


def test_field_error_carries_the_path_and_moves_inside_a_prefix():
    err = FieldError("disturbances.action[0].std", "must be >= 0, got -1")
    assert str(err) == "disturbances.action[0].std: must be >= 0, got -1"
    inner = err.within("env")
    assert (inner.path, inner.reason) == ("env.disturbances.action[0].std", "must be >= 0, got -1")
    assert str(FieldError("", "bad").within("env")) == "env: bad"
    assert str(FieldError("", "just a reason")) == "just a reason"
    again = pickle.loads(pickle.dumps(err))
    assert (again.path, again.reason) == (err.path, err.reason)


def test_join():
    assert V.join("", "env") == "env"
    assert V.join("env", "goal") == "env.goal"
    assert V.join("env.constraints", 2) == "env.constraints[2]"


def test_names_with_did_you_mean():
    assert V.name("rk4", "integrator", ("euler", "rk4")) == "rk4"
    assert _reason(V.name, "rk5", "integrator", ("euler", "rk4")) == (
        "integrator",
        "unknown value 'rk5'; allowed values are euler, rk4 (did you mean 'rk4'?)",
    )
    assert _reason(V.name, "zzz", "integrator", ("euler", "rk4")) == (
        "integrator",
        "unknown value 'zzz'; allowed values are euler, rk4",
    )
    assert _reason(V.name, 3, "on", ("state", "input")) == ("on", "expected one of state, input, got 3")


def test_check_keys():
    V.check_keys({"a": 1}, "env", ("a", "b"))
    assert _reason(V.check_keys, {"ctrl_frq": 1}, "env", ("ctrl_freq", "physics_freq")) == (
        "env.ctrl_frq",
        "unknown key; allowed keys are ctrl_freq, physics_freq (did you mean 'ctrl_freq'?)",
    )
    assert _reason(V.check_keys, {"bond": 1}, "c", ("type", "bound"), where="for a abs_bound constraint") == (
        "c.bond",
        "unknown key for a abs_bound constraint; allowed keys are type, bound (did you mean 'bound'?)",
    )
    assert _reason(V.check_keys, {"x": 1}, "", ("ctrl_freq",), what="option")[1] == (
        "unknown option; allowed options are ctrl_freq"
    )


def test_booleans_and_strings_are_not_guessed():
    assert V.boolean(np.bool_(True), "flag") is True
    for value in (1, "yes", "true", None):
        assert _reason(V.boolean, value, "flag") == ("flag", f"expected true or false, got {value!r}")
    assert V.string("xz", "plane") == "xz"
    assert _reason(V.string, 1, "plane") == ("plane", "expected a string, got 1")


def test_integers():
    assert V.integer(50, "f") == 50 and V.integer(50.0, "f") == 50 and V.integer(np.int32(7), "f") == 7
    assert type(V.integer(np.int64(7), "f")) is int
    assert _reason(V.integer, "50", "ctrl_freq") == ("ctrl_freq", "expected an integer, got '50'")
    assert _reason(V.integer, 15.5, "f") == ("f", "expected an integer, got 15.5")
    assert _reason(V.integer, True, "f") == ("f", "expected an integer, got True")
    assert _reason(V.integer, float("inf"), "f") == ("f", "expected an integer, got inf")
    assert _reason(V.integer, 0, "f", minimum=1) == ("f", "must be a positive integer, got 0")
    assert _reason(V.integer, -1, "f", minimum=0) == ("f", "must be a non-negative integer, got -1")
    assert _reason(V.integer, 2, "f", minimum=3) == ("f", "must be an integer >= 3, got 2")


def test_numbers():
    assert V.number(2, "x") == 2.0 and type(V.number(np.float32(0.5), "x")) is float
    assert V.number(np.asarray(1.5), "x") == 1.5  # a 0-d array
    assert V.number(float("-inf"), "low", allow_inf=True) == float("-inf")
    assert V.number("1e-3", "x", yaml_strings=True) == 0.001
    assert _reason(V.number, "1e-3", "x") == ("x", "expected a finite number, got '1e-3'")
    assert _reason(V.number, "big", "x", allow_inf=True) == ("x", "expected a number, got 'big'")
    assert _reason(V.number, True, "x") == ("x", "expected a finite number, got True")
    assert _reason(V.number, float("nan"), "x", allow_inf=True) == ("x", "must be finite, got nan")
    assert _reason(V.number, float("inf"), "x") == ("x", "must be finite, got inf")
    assert V.positive(0.1, "x") == 0.1 and V.non_negative(0, "x") == 0.0
    assert _reason(V.positive, 0, "tol") == ("tol", "must be positive, got 0")
    assert _reason(V.non_negative, -1, "env.disturbances.action[0].std") == (
        "env.disturbances.action[0].std",
        "must be >= 0, got -1",
    )


def test_vectors():
    np.testing.assert_array_equal(V.vector([1, 2], "goal", 2), [1.0, 2.0])
    assert V.vector((1, 2), "goal", 2).dtype == np.float64
    np.testing.assert_array_equal(V.vector(0.5, "mask", 3, broadcast=True), [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(V.vector(np.arange(3), "v"), [0.0, 1.0, 2.0])
    assert _reason(V.vector, [0.0, 1.0, 2.0], "offset", 2) == ("offset", "expected 2 values, got 3: [0.0, 1.0, 2.0]")
    assert _reason(V.vector, [0.1, 0.1], "std", 4, broadcast=True) == (
        "std",
        "expected a number or 4 values, got 2: [0.1, 0.1]",
    )
    assert _reason(V.vector, "big", "std", broadcast=True) == (
        "std",
        "expected a number or a list of numbers, got 'big'",
    )
    assert _reason(V.vector, 1.0, "goal", 2) == ("goal", "expected 2 values, got 1.0")
    assert _reason(V.vector, [[1.0]], "goal") == ("goal", "expected a list of numbers, got [[1.0]]")
    assert _reason(V.vector, [0, "a"], "goal") == ("goal[1]", "expected a finite number, got 'a'")
    assert _reason(V.vector, [0, float("nan")], "goal", allow_inf=True) == ("goal[1]", "must be finite, got nan")


def test_matrices():
    np.testing.assert_array_equal(V.matrix([[1, 0], [0, 1]], "P", 2, 2), np.eye(2))
    assert V.matrix([[1, 2, 3]], "A", cols=3).shape == (1, 3)
    assert _reason(V.matrix, [[1, 0, 0]], "A", cols=2) == (
        "A",
        "expected a matrix of shape (rows, 2), got shape (1, 3)",
    )
    assert _reason(V.matrix, [[1.0]], "P", 2, 2) == ("P", "expected a matrix of shape (2, 2), got shape (1, 1)")
    assert _reason(V.matrix, [[1.0, 0.0], [0.0]], "Q") == (
        "Q",
        "expected a matrix (a list of equal-length lists of numbers), got rows of lengths [1, 2]",
    )
    assert _reason(V.matrix, [1.0, 0.0], "A")[1].startswith("expected a matrix (a list of equal-length lists")
    assert _reason(V.matrix, [[1.0, "x"]], "A") == ("A[0][1]", "expected a finite number, got 'x'")


def test_weight_matrices_from_a_diagonal_or_a_full_matrix():
    np.testing.assert_array_equal(V.weight_matrix([1.0, 0.5], "Q", 2), np.diag([1.0, 0.5]))
    full = [[2.0, 0.5], [0.5, 1.0]]
    np.testing.assert_array_equal(V.weight_matrix(full, "Q", 2), np.array(full))
    np.testing.assert_array_equal(V.weight_matrix((3.0, 0.0), "q", 2, diagonal_only=True), np.diag([3.0, 0.0]))
    assert V.weight_matrix([1.0, 2.0], "Q", 2).dtype == np.float64
    assert _reason(V.weight_matrix, [1.0, 1.0, 1.0], "Q", 2) == (
        "Q",
        "expected 2 diagonal values or an (2, 2) matrix, got shape (3,)",
    )
    assert _reason(V.weight_matrix, [[1.0, 2.0], [0.0, 1.0]], "Q", 2)[1].startswith(
        "must be symmetric positive semidefinite"
    )
    assert _reason(V.weight_matrix, [-1.0], "R", 1)[1].startswith("must be symmetric positive semidefinite")
    assert _reason(V.weight_matrix, [1.0], "c.q_diag", 2, diagonal_only=True) == (
        "c.q_diag",
        "expected 2 values, got 1: [1.0]",
    )
    assert _reason(V.weight_matrix, [[1.0, 0.0], [0.0, 1.0]], "c.q_diag", 2, diagonal_only=True) == (
        "c.q_diag",
        "expected 2 values, got [[1.0, 0.0], [0.0, 1.0]]",
    )
    assert _reason(V.weight_matrix, [1.0, -0.1], "c.q_diag", 2, diagonal_only=True) == (
        "c.q_diag",
        "weights must be >= 0, got [1.0, -0.1]",
    )


def test_show_cuts_long_values():
    assert V.show(np.arange(3)) == "[0, 1, 2]"
    assert len(V.show(list(range(100)))) == 80 and V.show(list(range(100))).endswith("...")
