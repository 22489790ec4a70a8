import numpy as np
import pytest
from tensortouch.contracts.errors import CalibrationError
from tensortouch.runtime.stages.correction import ForceCorrection, apply_output


def gain_model(path, n_in, gain):
    from onnx import TensorProto, helper, numpy_helper, save

    w = numpy_helper.from_array(np.zeros((n_in, 1), np.float32), "w")
    b = numpy_helper.from_array(np.array([gain], np.float32), "b")
    g = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["m"]), helper.make_node("Add", ["m", "b"], ["y"])],
                          "gain", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", n_in])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 1])], [w, b])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    save(m, str(path))
    return path


def test_zero_force_stays_zero_even_if_model_adds():
    forces = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, -1.0]])
    out = apply_output(forces, np.array([[5.0, 5, 5], [1, 2, 3]]), "force", 5.0)
    assert np.all(out[0] == 0.0) and np.allclose(out[1], [1, 2, 3])
    g = apply_output(forces, np.array([[3.0], [-2.0]]), "gain", 5.0)
    assert np.all(g == 0.0)  # negative gain clipped to zero, zero row stays zero


def test_onnx_gain_correction(tmp_path):
    corr = ForceCorrection(gain_model(tmp_path / "c.onnx", 3, 1.25), {"inputs": ["fmag", "u", "v"], "output": "gain"})
    f = np.array([[0.0, 0.0, -2.0], [0.0, 0.0, 0.0]])
    out = corr(f, np.array([[0.5, 0.5], [0.1, 0.1]]), np.zeros((2, 2)))
    assert np.allclose(out[0], [0, 0, -2.5]) and np.all(out[1] == 0)


def test_identity_without_model():
    corr = ForceCorrection(None, None)
    f = np.array([[1.0, 2.0, 3.0]])
    assert not corr.enabled and np.array_equal(corr(f, np.zeros((1, 2)), np.zeros((1, 2))), f)


def test_bad_spec_and_corrupt_file(tmp_path):
    path = gain_model(tmp_path / "c.onnx", 3, 1.0)
    with pytest.raises(CalibrationError, match="correction.inputs"):
        ForceCorrection(path, {"inputs": ["pressure"], "output": "gain"})
    with pytest.raises(CalibrationError, match="expected \\[N, 2\\]"):
        ForceCorrection(path, {"inputs": ["u", "v"], "output": "gain"})
    (tmp_path / "bad.onnx").write_bytes(b"garbage")
    with pytest.raises(CalibrationError, match="cannot load the correction model"):
        ForceCorrection(tmp_path / "bad.onnx", {"inputs": ["fmag"], "output": "gain"})
