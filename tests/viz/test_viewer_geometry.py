"""The viewer's geometry (plain arrays, no Rerun): label meshes where the voxels are, image
planes where the probe's pixels are, arms through their joint origins, reconstructed voxels at
their centres."""

from __future__ import annotations

import numpy as np
import torch

from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.viewer.geometry import (
    arm_joint_origins,
    image_quads,
    mask_surface,
    patient_surfaces,
    to_frame,
    voxel_centres,
)


def test_a_ball_meshes_to_its_radius_in_patient_metres_facing_out():
    spacing, origin = 0.002, np.array([-0.1, 0.05, 0.2])
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = origin
    g = np.stack(np.meshgrid(*[np.arange(40)] * 3, indexing="ij"), -1)
    centre_idx, r_vox = np.array([20, 18, 22]), 10
    mask = ((g - centre_idx) ** 2).sum(-1) <= r_vox**2
    mesh = mask_surface("ball", mask, affine, resolution=spacing)
    centre = origin + centre_idx * spacing
    d = mesh.vertices - centre
    r = np.linalg.norm(d, axis=1)
    # the 0.5 iso-surface of a voxel ball lies within a voxel of its radius
    assert abs(r.mean() - r_vox * spacing) < spacing and r.max() - r.min() < 2 * spacing
    assert ((d * mesh.normals).sum(1) > 0).all()  # normals point out
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    facing = (np.cross(b - a, c - a) * (a - centre)).sum(1)
    assert (facing > 0).mean() > 0.99  # triangles wind counter-clockwise seen from outside
    # coarser sampling gives fewer faces (the decimation) around the same ball
    coarse = mask_surface("ball", mask, affine, resolution=3 * spacing)
    assert len(coarse.faces) < len(mesh.faces) / 4
    assert abs(np.linalg.norm(coarse.vertices - centre, axis=1).mean() - r_vox * spacing) < 0.004
    assert mask_surface("none", np.zeros((4, 4, 4), bool), affine, spacing) is None


def test_patient_surfaces_put_the_target_vertebra_at_its_landmark(small_phantom):
    p = small_phantom
    meshes = {m.name: m for m in patient_surfaces(p.labels.numpy(), p.affine, "L4")}
    assert set(meshes) == {"skin", "bone", "L4"}
    c = p.landmarks.vertebra("L4").centre
    l4 = meshes["L4"].vertices
    # the body centroid lies inside the vertebra's extent; the mesh spans a vertebra's size
    assert (l4.min(0) < c).all() and (c < l4.max(0)).all()
    assert 0.03 < np.ptp(l4[:, 0]) < 0.12
    # the skin encloses the bone: the back's skin (smallest y) is behind every bone vertex
    assert meshes["skin"].vertices[:, 1].min() < meshes["bone"].vertices[:, 1].min()


def test_image_quads_map_each_pixel_centre_to_its_probe_frame_position():
    for probe in (ProbeGeometry.linear_2d(), ProbeGeometry.volume_3d()):
        quads = image_quads(probe)
        assert len(quads) == probe.elevation_px
        x, z = probe.lateral_positions().numpy(), probe.depth_positions().numpy()
        ys = probe.elevation_positions().numpy()
        for q, y in zip(quads, ys, strict=True):
            for j, i in [(0, 0), (probe.depth_px - 1, 3), (7, probe.width_px - 1)]:
                u, v = (i + 0.5) / probe.width_px, (j + 0.5) / probe.depth_px
                # bilinear position of texcoord (u, v) on the quad (corners in texcoord order)
                t = q.texcoords
                w = (1 - np.abs(t[:, 0] - u)) * (1 - np.abs(t[:, 1] - v))
                pos = (w[:, None] * q.vertices).sum(0)
                np.testing.assert_allclose(pos, [x[i], y, z[j]], atol=1e-7)


def test_arm_polyline_runs_from_the_base_to_the_tool_tip():
    from sonogym.robots import PROBE_TOOL, Arm, ArmConfig

    base = torch.eye(4)
    base[:3, 3] = torch.tensor([0.4, -0.5, 0.1])
    arm = Arm(ArmConfig(model="kuka_med14", tool=PROBE_TOOL), base_pose=base)
    q = arm.default_joints(2)
    q[1] += 0.3
    pts = arm_joint_origins(arm, q, env=1)
    np.testing.assert_allclose(pts[0], [0.4, -0.5, 0.1], atol=1e-6)
    tip, _ = arm.fk(q)
    np.testing.assert_allclose(pts[-1], tip[1].numpy(), atol=1e-5)
    assert (np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6).all()  # no repeated origins


def test_voxel_centres_and_frames():
    vol = torch.zeros(5, 5, 5, dtype=torch.bool)
    vol[1, 2, 4] = vol[0, 0, 0] = True
    pts = voxel_centres(vol, np.array([0.1, 0.2, 0.3]), 0.003)
    np.testing.assert_allclose(
        sorted(pts.tolist()), [[0.1015, 0.2015, 0.3015], [0.1045, 0.2075, 0.3135]], atol=1e-7
    )
    rot = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # x -> y, y -> -x
    np.testing.assert_allclose(to_frame([1, 2, 3], rot, [[1.0, 0, 0]]), [[1, 3, 3]])
