"""Object placement in the grasp scene (tools/grasp/scene.py)."""
import numpy as np
import pytest


def test_placement_lets_both_objects_touch_one_pinch():
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp.scene import placement

    R, gap = 0.011, 0.005
    for r1, r2 in ((0.00109, 0.00109), (0.00109, 0.0015), (0.00109, 0.004), (0.004, 0.004)):
        x1, x2 = placement(r1, r2, R, gap)
        assert x2 - x1 >= r1 + r2 + gap - 1e-9
        # same sphere distance D closes on both: D = 2r + 2√(R² − x²) for each
        D1 = 2 * r1 + 2 * np.sqrt(R * R - x1 * x1)
        D2 = 2 * r2 + 2 * np.sqrt(R * R - x2 * x2)
        assert D1 == pytest.approx(D2, abs=1e-7)


def test_an_arm_translates_the_whole_hand_and_only_with_an_arm(tmp_path):
    """`SceneConfig.arm`: the palm is kinematic; `set_arm` moves every fingertip by the translation at
    once, `command_arm` + `step` gets there over the step; a scene without an arm refuses both."""
    pytest.importorskip("mujoco")
    pytest.importorskip("pinocchio")
    from tensortouch.tools.grasp import hand_model
    from tensortouch.tools.grasp.scene import Scene, SceneConfig

    spec = hand_model.HandSpec()
    urdf = hand_model.write_urdf(hand_model.default_urdf(), tmp_path / "hand.urdf", spec, 0.055, 0.0)
    joints = list(spec.thumb.joints + spec.index.joints)
    far = np.array([0.0, 0.0, 0.3])          # the objects well away from the fingers
    sc = Scene(str(urdf), joints, ("A", "pen"), far, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), SceneConfig(arm=True))
    q = np.zeros(len(joints))
    sc.set_hand(q)
    tips0 = [sc.tip_pose(i)[:3, 3].copy() for i in range(2)]
    t = np.array([0.004, -0.002, 0.001])
    sc.set_arm(t)
    np.testing.assert_allclose(sc.arm(), t, atol=1e-12)
    for i in range(2):
        np.testing.assert_allclose(sc.tip_pose(i)[:3, 3] - tips0[i], t, atol=1e-9)
    sc.command_arm(t + [0.002, 0, 0])
    sc.step(0.02)
    np.testing.assert_allclose(sc.arm(), t + [0.002, 0, 0], atol=1e-12)
    fixed = Scene(str(urdf), joints, ("A", "pen"), far, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    np.testing.assert_allclose(fixed.arm(), 0.0)
    with pytest.raises(ValueError, match="no arm"):
        fixed.set_arm(t)
    with pytest.raises(ValueError, match="no arm"):
        fixed.command_arm(t)


def test_opened_moves_the_fingertips_along_the_normal_without_touching_the_simulation(tmp_path):
    """`Scene.opened(q, n, mm)`: the thumb tip moves ≈ mm along +n and the index tip along −n (a
    negative mm closes past q: `TrialConfig.squeeze_mm`); the running simulation's joints stay."""
    pytest.importorskip("mujoco")
    pytest.importorskip("pinocchio")
    from tensortouch.tools.grasp import hand_model
    from tensortouch.tools.grasp.scene import Scene

    spec = hand_model.HandSpec()
    urdf = hand_model.write_urdf(hand_model.default_urdf(), tmp_path / "hand.urdf", spec, 0.055, 0.0)
    joints = list(spec.thumb.joints + spec.index.joints)
    sc = Scene(str(urdf), joints, ("A", "A"), np.array([0.0, 0.0, 0.3]), np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    q = np.full(len(joints), 0.3)
    sc.set_hand(q)
    tips = [sc.tip_pose(i)[:3, 3].copy() for i in range(2)]
    n = (tips[0] - tips[1]) / np.linalg.norm(tips[0] - tips[1])
    qpos = sc.data.qpos.copy()
    for mm in (1.0, -1.0):
        q2 = sc.opened(q, n, mm)
        np.testing.assert_array_equal(sc.data.qpos, qpos)
        sc.set_hand(q2)
        moved = [sc.tip_pose(i)[:3, 3] - tips[i] for i in range(2)]
        assert moved[0] @ n == pytest.approx(mm / 1000.0, abs=2e-4)
        assert moved[1] @ n == pytest.approx(-mm / 1000.0, abs=2e-4)
        sc.set_hand(q)
        qpos = sc.data.qpos.copy()
