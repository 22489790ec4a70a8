"""Gel line contact (tools/grasp/dome_contact.py): depth profile, shear, hand-worked values, FE of the twin
dome."""
import numpy as np
import pytest
from tensortouch.tools.grasp.dome_contact import DomeContactConfig, ObjectContact, displacement
from tensortouch.tools.twin.geometry import GelSurface


def test_line_contact_depth_profile_and_shear():
    gel = GelSurface()
    pts = gel.samples(0.4)
    nrm = gel.normals(pts)
    apex = np.array([0, 0, gel.top_z])
    ob = ObjectContact(apex, np.array([0, 1.0, 0]), 1.09, 1.0, np.array([0.3, 0, 0]))
    u = displacement(gel, pts, nrm, [ob])
    i0 = int(np.argmin(np.linalg.norm(pts - apex, axis=1)))
    assert -u[i0] @ nrm[i0] == pytest.approx(1.0, abs=0.05)       # depth d at the contact line
    assert u[i0, 0] == pytest.approx(0.3, abs=0.02)                 # the skin follows the object
    far = np.abs(pts[:, 0]) > 8
    assert np.abs(u[far]).max() < 0.35
    along = (np.abs(pts[:, 0]) < 0.3) & (np.abs(pts[:, 1]) > 9)     # the straight object leaves the dome
    assert np.abs(u[along] @ np.array([0, 0, 1.0])).max() < 0.2
    assert np.allclose(displacement(gel, pts, nrm, []), 0)


def test_line_contact_profile_hand_worked_values():
    """Across a cylinder pressed at the apex: the object's shape inside the contact half-width
    b = √(R* d), d/2 at its edge, then (d/2)·exp(−(s − b)/λ) with s the arc distance on the dome."""
    gel = GelSurface()
    R, zc = gel.profile.radius_mm, gel.profile.center_z_mm
    a, d, lam = 4.0, 1.0, DomeContactConfig().tail_mm
    Rs = 1.0 / (1.0 / a + 1.0 / R)
    b = np.sqrt(Rs * d)
    s = np.array([0.0, 0.5 * b, b, b + lam, b + 2 * lam])          # arc distances across the object
    pts = np.stack([R * np.sin(s / R), np.zeros_like(s), zc + R * np.cos(s / R)], 1)
    nrm = (pts - [0, 0, zc]) / R
    ob = ObjectContact(np.array([0, 0, gel.top_z]), np.array([0, 1.0, 0]), a, d, np.zeros(3))
    w = -np.einsum("ij,ij->i", displacement(gel, pts, nrm, [ob]), nrm)
    want = [d, d - (0.5 * b) ** 2 / (2 * Rs), d / 2, d / 2 / np.e, d / 2 / np.e ** 2]
    assert w == pytest.approx(want, abs=1e-6)


@pytest.mark.slow
def test_line_contact_profile_matches_fe_of_the_twin_dome():
    """The fitted profile against FE (tools.fe) of the twin's standard dome: a pen-sized cylinder
    (radius 4 mm) pressed 0.6 and 1.2 mm across its apex; normal displacement of the surface nodes
    within 1 mm of the cross-section and 8 mm of the contact line."""
    from tensortouch.tools.fe import GelGeometry, Indenter, Keypoint, MeshSettings, Scenario, solve

    fe_gel = GelGeometry()
    ind = Indenter(name="pen", shape="cylinder", params={"radius": 4.0, "length": 40.0},
                   position=[0.0, 0.0, fe_gel.top_z], keypoints=[Keypoint([0.0, 0.0, -0.6]), Keypoint([0.0, 0.0, -1.2])])
    res = solve(Scenario(gel=fe_gel, mesh=MeshSettings(size_top=0.6), indenters=[ind], name="pen-across-apex").validate())
    gel = GelSurface()
    R, zc = gel.profile.radius_mm, gel.profile.center_z_mm
    P = res.nodes[res.surface_nodes]
    nrm = P - [0.0, 0.0, zc]
    rad = np.linalg.norm(nrm, axis=1)
    nrm /= rad[:, None]
    sel = (np.abs(rad - R) < 0.05) & (np.abs(P[:, 0]) < 1.0) & (np.abs(P[:, 1]) < 8.0)
    assert sel.sum() > 20
    for j, d in enumerate((0.6, 1.2)):
        w_fe = -np.einsum("ij,ij->i", res.U[j][res.surface_nodes][sel], nrm[sel])
        ob = ObjectContact(np.array([0.0, 0.0, gel.top_z]), np.array([1.0, 0.0, 0.0]), 4.0, d, np.zeros(3))
        w = -np.einsum("ij,ij->i", displacement(gel, P[sel], nrm[sel], [ob]), nrm[sel])
        assert np.sqrt(np.mean((w - w_fe) ** 2)) < 0.05, (d, np.sqrt(np.mean((w - w_fe) ** 2)))
