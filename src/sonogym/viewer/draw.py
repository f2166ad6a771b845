"""Log the viewer's pieces to a Rerun recording: one entity layout for every source (an env, a
run's saved episodes, a dataset), so the same blueprint shows them all.

Arrays are copied when logged: Rerun batches rows and may keep a view of the array it was given
until it flushes, while an env updates its state tensors (and their NumPy views) in place.

Entities (``world`` is the patient frame {P} in metres, RAS, drawn with -y up: the patient lies
prone, the back up):

* ``world/patient/{skin,bone,<target>}``: surface meshes (static);
* ``world/probe``: the probe frame {U} (axes), ``world/probe/image[/slice_<e>]`` its image
  planes textured with the live ultrasound, ``world/probe_path`` the face's path;
* ``world/goal``: the goal frame (axes); surgery: ``world/goal/c_drill`` (the corridor
  cylinder), ``world/goal/c_free`` (the plane p_z = -l that bounds C_free), ``world/plan``
  (the planned trajectory, entry to target), ``world/drill`` (the tip frame {D}) and
  ``world/drill_path``;
* ``world/<arm>``: an arm's links (a polyline through its joint origins) and joints;
* ``world/reconstruction``: reconstructed bone points;
* ``image/us[/slice_<e>]``, ``image/labels[/slice_<e>]``: the 2-D images;
* ``series/<name>``: scalars over the ``step`` timeline.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from sonogym.anatomy.labels import BONE_IDS, LABELS, LUMBAR_VERTEBRAE
from sonogym.viewer.geometry import ImageQuad, SurfaceMesh

#: The timeline every source logs on: env steps (0 = the start state), or dataset frames.
TIMELINE = "step"

MESH_COLORS = {"skin": (225, 175, 150, 70), "bone": (235, 228, 205, 255)}
TARGET_COLOR = (250, 190, 40, 255)
ARM_COLORS = {"kuka_med14": (240, 120, 30), "franka_fr3": (200, 200, 210)}
PROBE_PATH_COLOR = (230, 40, 40)
DRILL_COLOR = (220, 30, 30)
GOAL_COLOR = (40, 220, 40)
CORRIDOR_COLOR = (60, 160, 255)
POINTS_COLOR = (40, 230, 90)

#: Label colours of the 2-D label images (other ids: a fixed colour per id).
_LABEL_COLORS = {
    0: (0, 0, 0),
    118: (240, 170, 150),
    119: (240, 220, 110),
    120: (150, 50, 50),
    121: (70, 110, 230),
    122: (60, 210, 220),
}


def set_step(rec: rr.RecordingStream, step: int) -> None:
    rec.set_time(TIMELINE, sequence=int(step))


def log_frame_conventions(rec: rr.RecordingStream) -> None:
    """{P} is right-handed with -y (posterior) up: a prone patient's back faces the viewer."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)


def log_surfaces(rec: rr.RecordingStream, meshes: Sequence[SurfaceMesh]) -> None:
    """Patient surfaces (static): translucent skin, bone, the target vertebra highlighted."""
    for m in meshes:
        color = MESH_COLORS.get(m.name, TARGET_COLOR)
        rec.log(
            f"world/patient/{m.name}",
            rr.Mesh3D(
                vertex_positions=m.vertices,
                triangle_indices=m.faces,
                vertex_normals=m.normals,
                albedo_factor=color,
            ),
            static=True,
        )


def log_pose(
    rec: rr.RecordingStream, path: str, pos, rot, axis_length: float = 0.03, static=False
) -> None:
    """A frame (origin ``pos`` (3,), axes the columns of ``rot`` (3, 3)) with its axes drawn
    (x red, y green, z blue)."""
    rec.log(
        path,
        rr.Transform3D(translation=np.array(pos, np.float32), mat3x3=np.array(rot, np.float32)),
        rr.TransformAxes3D(axis_length),
        static=static,
    )


def _rgb(image: np.ndarray) -> np.ndarray:
    """A 2-D image in [0, 1] -> uint8 (H, W, 3)."""
    u = (np.clip(np.array(image, np.float32), 0, 1) * 255).round().astype(np.uint8)
    return np.repeat(u[..., None], 3, -1)


def slice_paths(base: str, n: int) -> list[str]:
    return [base] if n == 1 else [f"{base}/slice_{e}" for e in range(n)]


def log_image_planes(
    rec: rr.RecordingStream, quads: Sequence[ImageQuad], images: np.ndarray
) -> None:
    """The probe's image slices (E, H, W) in [0, 1] as textured quads in {U}, under
    ``world/probe`` (so they move with the probe's transform)."""
    for path, q, img in zip(
        slice_paths("world/probe/image", len(quads)), quads, images, strict=True
    ):
        rec.log(
            path,
            rr.Mesh3D(
                vertex_positions=q.vertices,
                triangle_indices=q.faces,
                vertex_texcoords=q.texcoords,
                albedo_texture=_rgb(img),
                face_rendering=rr.components.MeshFaceRendering.DoubleSided,
            ),
        )


def _label_color(i: int) -> tuple[int, int, int]:
    if i in _LABEL_COLORS:
        return _LABEL_COLORS[i]
    if i in LUMBAR_VERTEBRAE.values():
        return TARGET_COLOR[:3]
    if i in BONE_IDS:
        return (235, 228, 205)
    return ((i * 97) % 140 + 60, (i * 57) % 140 + 60, (i * 31) % 140 + 60)  # fixed per id


def label_annotations() -> rr.AnnotationContext:
    """Names and colours of every label id, for the label images: the lumbar vertebrae as the
    target in 3-D, other bone bone-white, the project's soft tissues as in ``_LABEL_COLORS``."""
    ids = [0, *sorted(LABELS)]
    return rr.AnnotationContext(
        [
            rr.AnnotationInfo(id=i, label=LABELS.get(i, "background"), color=_label_color(i))
            for i in ids
        ]
    )


def log_images_2d(
    rec: rr.RecordingStream, us: np.ndarray | None = None, labels: np.ndarray | None = None
) -> None:
    """Ultrasound (E, H, W) in [0, 1] and label (E, H, W) uint8 images, one entity per slice."""
    if us is not None:
        for path, img in zip(slice_paths("image/us", len(us)), us, strict=True):
            rec.log(path, rr.Image(_rgb(img)[..., 0]))
    if labels is not None:
        for path, img in zip(slice_paths("image/labels", len(labels)), labels, strict=True):
            rec.log(path, rr.SegmentationImage(np.array(img, np.uint8)))


def log_polyline(
    rec: rr.RecordingStream, path: str, points: np.ndarray, color, radius: float = 0.001
) -> None:
    rec.log(path, rr.LineStrips3D([np.array(points, np.float32)], radii=radius, colors=color))


def log_arm(rec: rr.RecordingStream, path: str, joints: np.ndarray, color) -> None:
    """An arm: links as a thick polyline through its joint origins (base to tool tip), joints
    as points."""
    rec.log(
        path,
        rr.LineStrips3D([joints.astype(np.float32)], radii=0.012, colors=color),
        rr.Points3D(joints.astype(np.float32), radii=0.018, colors=(60, 60, 70)),
    )


def log_surgery_plan(
    rec: rr.RecordingStream,
    goal_pos: np.ndarray,
    goal_rot: np.ndarray,
    entry: np.ndarray,
    target: np.ndarray,
    half_width: float,
    skin_distance: float,
) -> None:
    """The goal frame {G} at the target, the planned trajectory (entry -> target), C_drill (a
    cylinder of radius d/2 along z_G from p_z = -l to 0, wireframe) and the plane p_z = -l that
    bounds C_free (the half-space beyond it, away from the target), static."""
    log_pose(rec, "world/goal", goal_pos, goal_rot, 0.02, static=True)
    wire = rr.components.FillMode.MajorWireframe
    c_drill = rr.Cylinders3D(lengths=[skin_distance], radii=[half_width],
                             centers=[[0.0, 0.0, -skin_distance / 2]], colors=[CORRIDOR_COLOR],
                             fill_mode=wire)  # fmt: skip
    c_free = rr.Boxes3D(centers=[[0.0, 0.0, -skin_distance]], half_sizes=[[0.03, 0.03, 0.0]],
                        colors=[GOAL_COLOR], fill_mode=wire)  # fmt: skip
    rec.log("world/goal/c_drill", c_drill, static=True)
    rec.log("world/goal/c_free", c_free, static=True)
    rec.log(
        "world/plan",
        rr.LineStrips3D(
            [np.stack([entry, target]).astype(np.float32)], radii=0.0008, colors=[GOAL_COLOR]
        ),
        static=True,
    )


def log_points(
    rec: rr.RecordingStream, path: str, points: np.ndarray, color, radius: float = 0.0015
) -> None:
    rec.log(path, rr.Points3D(np.array(points, np.float32), radii=radius, colors=color))


def log_image_outlines(rec: rr.RecordingStream, quads: Sequence[ImageQuad]) -> None:
    """The outlines of the probe's image planes in {U} (static, under ``world/probe``): where
    the images would be when none are shown."""
    strips = [np.vstack([q.vertices, q.vertices[:1]]) for q in quads]
    rec.log(
        "world/probe/outline",
        rr.LineStrips3D(strips, radii=0.0005, colors=(200, 200, 200)),
        static=True,
    )


def log_series_names(rec: rr.RecordingStream, names: dict[str, Sequence[str]]) -> None:
    """Legend names of the series entities (static): {entity: one name per component}."""
    for path, n in names.items():
        rec.log(path, rr.SeriesLines(names=list(n)), static=True)


def log_scalars(rec: rr.RecordingStream, values: dict[str, float | Sequence[float]]) -> None:
    for path, v in values.items():
        rec.log(path, rr.Scalars(np.atleast_1d(np.array(v, np.float64))))


#: m, the 3-D view's eye distance from what it looks at.
EYE_DISTANCE = 0.35


def eye_offset(normal: np.ndarray) -> np.ndarray:
    """Where the 3-D view's eye starts relative to what it looks at: along ``normal`` (the
    axis it should face, taken from the patient's right or feet side) and above the back
    (-y), ``EYE_DISTANCE`` away."""
    normal = np.array(normal, np.float64)
    if normal @ np.array([1.0, 0.0, -1.0]) < 0:
        normal = -normal
    d = normal / np.linalg.norm(normal) + np.array([0.0, -1.0, 0.0])
    return EYE_DISTANCE * d / np.linalg.norm(d)


#: The axis a drill scene is seen along: the spine's (an axial view of the drilled vertebra,
#: between the arms on either side, with the drill's medial angle in view).
AXIAL = np.array([0.0, 0.0, 1.0])


def blueprint(
    image_paths: Sequence[str],
    series_paths: Sequence[str],
    eye: tuple[np.ndarray, np.ndarray] | None = None,
    text: str | None = None,
    scene: bool = True,
) -> rrb.Blueprint:
    """The 3-D scene (``scene``) on the left, its eye at ``eye`` = (position, target) in {P}
    (None: Rerun's default); on the right the 2-D images, one plot per series and the text
    document at ``text``."""
    images = [rrb.Spatial2DView(origin=p, name=p.removeprefix("image/")) for p in image_paths]
    plots = [rrb.TimeSeriesView(origin=p, name=p.removeprefix("series/")) for p in series_paths]
    right = []
    if text is not None:
        right.append(rrb.TextDocumentView(origin=text, name=text))
    if images:
        right.append(rrb.Grid(*images))
    if plots:
        right.append(rrb.Grid(*plots))
    controls = None
    if eye is not None:
        controls = rrb.EyeControls3D(
            position=np.array(eye[0], np.float64),
            look_target=np.array(eye[1], np.float64),
            eye_up=(0.0, -1.0, 0.0),
        )
    view = rrb.Spatial3DView(origin="world", name="scene", eye_controls=controls)
    if not scene:
        layout = rrb.Vertical(*right)
    elif right:
        layout = rrb.Horizontal(view, rrb.Vertical(*right), column_shares=[3, 2])
    else:
        layout = view
    # the time cursor follows the newest step: live, the current state; from a file, the last
    time = rrb.TimePanel(timeline=TIMELINE, play_state="following")
    return rrb.Blueprint(layout, time, collapse_panels=True)
