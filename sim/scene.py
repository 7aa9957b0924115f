"""Frozen simulation scenes: a target object made of planar textured faces, a
ChArUco board fixed beside it, a textured table, and the start viewpoint.

Scenes live in config/scenes/<name>.yaml (mm/deg at that edge) and are parsed
once, through `supervisor.yamlschema.Node`, into the frozen `Scene` below (SI).

Frames: the *scene* frame has its origin on the table (z = 0 is the table
surface, z up), and is placed in the robot base frame by `T_base_scene`. Every
face has its own frame with the same convention as the ChArUco board frame:
origin at the top-left corner of its texture rectangle, x along texture columns,
y along rows, z *into* the surface, so the outward normal is -z and a camera
sees the face only from its z < 0 side. The *target* frame is the board frame.

Object kinds (each expands to planar faces):
  box    center_mm, size_mm [x, y, z], rpy_deg           -> 6 rectangles
  plate  center_mm, size_mm [w, h], thickness_mm, rpy_deg -> a thin box
  bone   from_mm, to_mm, radii_mm [r0..rn], sides, roll_deg
         -> a generalised prism: `sides` trapezoids per segment + 2 end caps
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.textures import ReliefParams, TextureParams
from supervisor.errors import ConfigError
from supervisor.geometry import inv_T, make_T, rpy_to_R, transform_from_config
from supervisor.localization.fiducial import BoardSpec
from supervisor.paths import SCENES_DIR
from supervisor.yamlschema import Node, decode_text, load_yaml_text, read_bounded

_BOX_MARGIN_M = 0.004  # target box margin around the object's faces
_BOX_FLOOR_M = 0.0015  # the target box stops this far above the table (keeps ground points out)


@dataclass(frozen=True)
class View:
    """Start viewpoint about the pivot (see supervisor.motion.paths.start_camera_pose)."""

    radius: float  # m
    elevation: float  # rad
    heading: float  # rad


@dataclass(frozen=True)
class Material:
    """Appearance of a surface: albedo pattern, relief and gloss (Blinn-Phong)."""

    name: str
    texture: TextureParams
    relief: ReliefParams
    specular: float  # Blinn-Phong weight, in units of a white Lambertian surface
    shininess: float  # Blinn-Phong exponent


@dataclass(frozen=True)
class Lighting:
    """Camera-mounted point light and exposure."""

    ambient: float
    diffuse: float
    exposure: float  # DN = 255 * exposure * radiance
    falloff_ref: float  # m; inverse-square falloff is 1 at this distance


@dataclass(frozen=True)
class Sensor:
    """Per-frame illumination drift and sensor effects."""

    noise_dn: float  # Gaussian read noise std, DN
    blur_px: float  # Gaussian optical blur sigma, px (0 = none)
    drift: float  # relative gain drift amplitude with frame_index
    offset_dn: float  # offset drift amplitude, DN


@dataclass(frozen=True)
class Optics:
    """Lens and pixel effects a scene may opt into (all off: the pinhole camera with point-sampled
    textures that every suite-v2 scene uses, whose renders stay bit-identical).

    - `aperture`: entrance-pupil diameter (m); > 0 turns on depth of field. A point at depth z
      images as a blur disk of diameter fx * aperture * |1/z - 1/focus| pixels (thin lens,
      z >> focal length), drawn as a Gaussian of the disk's variance (sigma = diameter / 4).
    - `focus`: the in-focus distance (m); None = the scene's view radius (focused on the pivot
      at the start view, as an operator would set it).
    - `footprint_filter`: each pixel integrates the texture over its footprint on the surface.
      Toward edge-on that footprint stretches by 1/cos(obliquity) across the tilt, so texture
      finer than the stretched footprint averages away (the mip level alone, chosen by depth,
      only accounts for distance).
    """

    aperture: float = 0.0
    focus: float | None = None
    footprint_filter: bool = False

    @property
    def active(self) -> bool:
        return self.aperture > 0 or self.footprint_filter


@dataclass(frozen=True, eq=False)
class Face:
    """A planar convex polygon inside a texture rectangle of `size` (w, h) metres."""

    name: str
    kind: str  # "object" | "board" | "ground"
    T_scene_face: np.ndarray
    size: tuple[float, float]
    polygon: np.ndarray  # (N, 2) vertices in the face plane, metres, inside [0, w] x [0, h]
    material: Material
    texel: float  # m per texel at full resolution
    seed: int

    @property
    def normal_scene(self) -> np.ndarray:
        """Outward unit normal in the scene frame."""
        return -self.T_scene_face[:3, 2]

    def vertices_scene(self) -> np.ndarray:
        """(N, 3) polygon vertices in the scene frame."""
        P = np.column_stack([self.polygon, np.zeros(len(self.polygon)), np.ones(len(self.polygon))])
        return (P @ self.T_scene_face.T)[:, :3]


@dataclass(frozen=True, eq=False)
class Scene:
    """A parsed scene (SI units). See the module docstring for frames."""

    name: str
    seed: int
    sha256: str
    source: Path
    description: str
    T_base_scene: np.ndarray
    pivot: np.ndarray  # (3,) scene frame, m
    view: View
    board: BoardSpec
    T_scene_board: np.ndarray
    faces: tuple[Face, ...]  # the target object's faces
    board_face: Face
    ground: Face
    lighting: Lighting
    sensor: Sensor
    optics: Optics = Optics()

    @property
    def focus_distance(self) -> float:
        """m: where the lens is focused (the view radius unless the scene says otherwise)."""
        return self.view.radius if self.optics.focus is None else self.optics.focus

    @property
    def all_faces(self) -> tuple[Face, ...]:
        return (self.ground, self.board_face, *self.faces)

    @property
    def T_base_board(self) -> np.ndarray:
        return self.T_base_scene @ self.T_scene_board

    def reference_point_in_target(self) -> np.ndarray:
        """(3,) centre of the target object's bounding box in the target (board) frame, metres:
        the point at which localization's translation error is measured."""
        V = np.vstack([f.vertices_scene() for f in self.faces])
        centre = (V.min(axis=0) + V.max(axis=0)) / 2
        T_board_scene = inv_T(self.T_scene_board)
        return T_board_scene[:3, :3] @ centre + T_board_scene[:3, 3]

    def target_box_in_target(self) -> tuple[np.ndarray, np.ndarray]:
        """(T_target_box, half_extents): a box in the target (board) frame enclosing the target
        object's faces with a small margin, axis-aligned with the scene frame and stopping
        just above the table so table texture is not part of the model."""
        V = np.vstack([f.vertices_scene() for f in self.faces])
        lo = V.min(axis=0) - _BOX_MARGIN_M
        hi = V.max(axis=0) + _BOX_MARGIN_M
        lo[2] = max(lo[2], _BOX_FLOOR_M)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        T_target_box = inv_T(self.T_scene_board) @ make_T(np.eye(3), centre)
        return T_target_box, half


# ---------------------------------------------------------------------------- loading

def list_scenes() -> list[str]:
    """Names of the shipped scenes (config/scenes/*.yaml), sorted."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))


def load_scene(name_or_path: str | Path) -> Scene:
    """A shipped scene by bare name, or any scene YAML by path."""
    s = str(name_or_path)
    if s.endswith((".yaml", ".yml")) or "/" in s or "\\" in s:
        path = Path(s)
    else:
        path = SCENES_DIR / f"{s}.yaml"
        if not path.is_file():
            raise ConfigError(SCENES_DIR, "scene",
                              f"unknown scene {s!r}; available in {SCENES_DIR}: {', '.join(list_scenes())}")
    raw = read_bounded(path, what="scene file")
    root = Node(load_yaml_text(decode_text(raw, path), path), path)
    return _parse(root, path.stem, hashlib.sha256(raw).hexdigest(), path)


def _parse(root: Node, name: str, sha: str, source: Path) -> Scene:
    seed = root.integer("seed", min=0)
    description = root.string("description", "(no description)")
    T_base_scene = transform_from_config(root, "placement")
    pivot = root.vector("pivot_mm", 3) / 1000.0
    v = root.child("view")
    view = View(v.number("radius_mm", min=50, max=1500) / 1000.0,
                math.radians(v.number("elevation_deg", min=0, max=90)),
                math.radians(v.number("heading_deg", min=-360, max=360)))
    v.done()
    texel = root.number("texel_mm", 0.2, min=0.02, max=5.0) / 1000.0
    lighting = _lighting(root.child("lighting", {}))
    sensor = _sensor(root.child("sensor", {}))
    optics = _optics(root.child("optics", {}))

    materials = {mname: _material(mname, node) for mname, node in root.children("materials")}

    def material(node: Node, key: str = "material") -> Material:
        m = node.string(key)
        if m not in materials:
            raise node.error(key, f"unknown material {m!r}; defined: {', '.join(sorted(materials)) or 'none'}")
        return materials[m]

    board, T_scene_board = _board(root.child("board"))
    bw, bh = board.size_m
    paper = Material("board", TextureParams(), ReliefParams(0.0, 1.0), 0.02, 5.0)
    board_face = Face("board", "board", T_scene_board, (bw, bh), _rect(bw, bh), paper, 1.0 / 5000.0, seed)

    g = root.child("ground")
    gw, gh = g.vector("size_mm", 2, min=10) / 1000.0
    gc = g.vector("center_mm", 2, default=[0.0, 0.0]) / 1000.0
    g_texel = g.number("texel_mm", 0.6, min=0.05, max=10) / 1000.0
    g_mat = material(g)
    g.done()
    # Ground frame: x = scene x, y = -scene y, z = -scene z (into the table); origin at its top-left.
    R_ground = np.diag([1.0, -1.0, -1.0])
    T_scene_ground = make_T(R_ground, [gc[0] - gw / 2, gc[1] + gh / 2, 0.0])
    ground = Face("ground", "ground", T_scene_ground, (gw, gh), _rect(gw, gh), g_mat, g_texel, seed + 1)

    faces: list[Face] = []
    for oname, o in root.children("objects"):
        kind = o.string("kind", choices=("box", "plate", "bone"))
        mat = material(o)
        if kind == "box":
            polys = _box_faces(o.vector("center_mm", 3) / 1000.0, o.vector("size_mm", 3, min=0.1) / 1000.0,
                               np.radians(o.vector("rpy_deg", 3, default=[0, 0, 0])))
        elif kind == "plate":
            w, h = o.vector("size_mm", 2, min=0.1) / 1000.0
            t = o.number("thickness_mm", 3.0, min=0.1) / 1000.0
            polys = _box_faces(o.vector("center_mm", 3) / 1000.0, np.array([w, h, t]),
                               np.radians(o.vector("rpy_deg", 3, default=[0, 0, 0])))
        else:
            radii = np.array(o.number_list("radii_mm", min=0.5, min_length=2)) / 1000.0
            polys = _bone_faces(o.vector("from_mm", 3) / 1000.0, o.vector("to_mm", 3) / 1000.0, radii,
                                o.integer("sides", 6, min=3, max=16), math.radians(o.number("roll_deg", 0.0)))
            if polys is None:
                raise o.error("to_mm", "must differ from from_mm")
        o.done()
        for k, (fname, pts, normal) in enumerate(polys):
            T, size, poly2 = _face_frame(pts, normal)
            faces.append(Face(f"{oname}.{fname}", "object", T, size, poly2, mat, texel,
                              seed + 1000 + 37 * len(faces) + k))
    if not faces:
        raise root.error("objects", "at least one object is required")
    root.done()
    return Scene(name, seed, sha, source, description, T_base_scene, pivot, view, board, T_scene_board,
                 tuple(faces), board_face, ground, lighting, sensor, optics)


def _material(name: str, n: Node) -> Material:
    blob = n.vector("blob_mm", 2, default=[1.0, 5.0], min=0.05)
    stroke = n.vector("stroke_mm", 2, default=[4.0, 15.0], min=0.1)
    tex = TextureParams(
        albedo=n.number("albedo", 0.6, min=0.02, max=0.98),
        contrast=n.number("contrast", 0.25, min=0.0, max=0.5),
        feature_mm=n.number("feature_mm", 1.5, min=0.05, max=100),
        blobs_per_cm2=n.number("blobs_per_cm2", 0.5, min=0.0, max=50),
        blob_mm=(float(blob[0]), float(blob[1])),
        strokes_per_cm2=n.number("strokes_per_cm2", 0.2, min=0.0, max=50),
        stroke_mm=(float(stroke[0]), float(stroke[1])),
    )
    relief = ReliefParams(n.number("bump_mm", 0.0, min=0.0, max=5.0), n.number("bump_scale_mm", 2.0, min=0.05, max=100))
    m = Material(name, tex, relief, n.number("specular", 0.0, min=0.0, max=5.0),
                 n.number("shininess", 20.0, min=1.0, max=2000.0))
    n.done()
    return m


def _lighting(n: Node) -> Lighting:
    out = Lighting(n.number("ambient", 0.12, min=0.0, max=1.0), n.number("diffuse", 0.88, min=0.0, max=2.0),
                   n.number("exposure", 0.8, min=0.05, max=10.0),
                   n.number("falloff_ref_mm", 350.0, min=10.0, max=5000.0) / 1000.0)
    n.done()
    return out


def _sensor(n: Node) -> Sensor:
    out = Sensor(n.number("noise_dn", 2.0, min=0.0, max=50.0), n.number("blur_px", 0.6, min=0.0, max=5.0),
                 n.number("drift", 0.03, min=0.0, max=0.5), n.number("offset_dn", 2.0, min=0.0, max=50.0))
    n.done()
    return out


def _optics(n: Node) -> Optics:
    focus = n.number("focus_mm", 0.0, min=0.0, max=5000.0)
    out = Optics(n.number("aperture_mm", 0.0, min=0.0, max=50.0) / 1000.0, focus / 1000.0 if focus > 0 else None,
                 n.boolean("footprint_filter", False))
    n.done()
    return out


def _board(n: Node) -> tuple[BoardSpec, np.ndarray]:
    dictionary = n.string("dictionary", "5x5_100", choices=("4x4_50", "4x4_100", "5x5_100", "6x6_250"))
    sq = n.number("square_mm", min=2.0, max=200.0)
    mk = n.number("marker_mm", min=1.0, max=200.0)
    if mk >= sq:
        raise n.error("marker_mm", f"must be smaller than square_mm ({sq:g}), got {mk:g}")
    spec = BoardSpec(n.integer("squares_x", min=3, max=20), n.integer("squares_y", min=3, max=20), sq / 1000.0,
                     mk / 1000.0, dictionary)
    T = transform_from_config(n, "pose")
    n.done()
    return spec, T


# ---------------------------------------------------------------------------- geometry

def _rect(w: float, h: float) -> np.ndarray:
    return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])


def _face_frame(pts: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, tuple[float, float], np.ndarray]:
    """Face frame (board convention) for a planar polygon with outward `normal`:
    x along the first edge, z = -normal; returns (T_scene_face, size, polygon 2D)."""
    z = -normal / np.linalg.norm(normal)
    x = pts[1] - pts[0]
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    local = (pts - pts[0]) @ R
    lo = local[:, :2].min(axis=0)
    origin = pts[0] + R[:, :2] @ lo
    poly = local[:, :2] - lo
    w, h = poly.max(axis=0)
    return make_T(R, origin), (float(w), float(h)), poly


def _box_faces(center: np.ndarray, size: np.ndarray, rpy: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Six outward-facing rectangles of an oriented box (scene frame)."""
    R = rpy_to_R(*rpy)
    half = size / 2
    out = []
    for axis, name in ((0, "x"), (1, "y"), (2, "z")):
        u, v = [a for a in range(3) if a != axis]
        for sign in (1.0, -1.0):
            corners = []
            for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis] = sign * half[axis]
                p[u] = cu * half[u]
                p[v] = cv * half[v]
                corners.append(center + R @ p)
            n = np.zeros(3)
            n[axis] = sign
            out.append((f"{'+' if sign > 0 else '-'}{name}", np.array(corners), R @ n))
    return out


def _bone_faces(p0: np.ndarray, p1: np.ndarray, radii: np.ndarray, sides: int,
                roll: float) -> list[tuple[str, np.ndarray, np.ndarray]] | None:
    """A generalised prism along p0->p1: rings of `sides` vertices with the given radii.
    Rings share orientation, so each side quad is a planar trapezoid."""
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    if length < 1e-6:
        return None
    a = axis / length
    ref = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    angles = roll + 2 * np.pi * np.arange(sides) / sides
    dirs = np.outer(np.cos(angles), e1) + np.outer(np.sin(angles), e2)
    centres = [p0 + a * length * k / (len(radii) - 1) for k in range(len(radii))]
    rings = [c + r * dirs for c, r in zip(centres, radii)]
    out = []
    for k in range(len(radii) - 1):
        for i in range(sides):
            j = (i + 1) % sides
            quad = np.array([rings[k][i], rings[k][j], rings[k + 1][j], rings[k + 1][i]])
            n = np.cross(quad[1] - quad[0], quad[3] - quad[0])
            mid = quad.mean(axis=0)
            c = centres[k] + a * (a @ (mid - centres[k]))
            if n @ (mid - c) < 0:
                n = -n
            out.append((f"s{k}.{i}", quad, n / np.linalg.norm(n)))
    out.append(("cap0", rings[0][::-1].copy(), -a))
    out.append(("cap1", rings[-1].copy(), a))
    return out
