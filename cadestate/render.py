"""Offscreen rasteriser: posed meshes + an OpenCV camera -> RGB, metric depth and instance ids.

OpenGL 3.3 through EGL (moderngl; Mesa llvmpipe when there is no GPU, no display needed).
Frames are those of :mod:`cadestate.geometry`: world +Y up, metres, OpenCV cameras, pixel (i, j)
centred at (i + 0.5, j + 0.5). A world point lands exactly where ``geometry.project`` puts it,
and row 0 of every returned array is the top of the image. Shading is Lambert + ambient,
two-sided (|cos|), with no culling, so mirrored instances and inconsistent winding render right.
A :class:`Renderer` owns one GL context; use it from the thread that created it.
"""

from __future__ import annotations

import ctypes.util
import weakref
from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import moderngl
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cadestate.geometry import quaternion_to_matrix

DEFAULT_COLOR = (0.8, 0.8, 0.8, 1.0)  # RGBA of meshes that carry no colour or material
CREASE_ANGLE = np.radians(30.0)  # from_trimesh smooths normals only across flatter edges
MAX_INSTANCE_ID = 2**24 - 2  # ids travel through a float32 attachment, exact up to here


@dataclass(frozen=True, eq=False)
class Material:
    """color: float32[4] RGBA in [0, 1] (3 values get alpha 1), multiplies the texture.
    texture: uint8[H, W, 3 | 4] or None, row 0 = top of the image, sampled at the mesh's uvs
    (OpenGL convention: uv (0, 0) is the image's bottom-left corner). Fragments with alpha < 0.5
    are discarded (cut-outs; there is no blending)."""

    color: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_COLOR, np.float32))
    texture: np.ndarray | None = None

    def __post_init__(self) -> None:
        color = np.asarray(self.color, np.float32).reshape(-1)
        if len(color) not in (3, 4):
            raise ValueError(f"Material.color must have 3 or 4 values, got {color.shape}")
        object.__setattr__(self, "color", _read_only(np.append(color, np.float32(1.0))[:4]))
        if self.texture is not None:
            tex = np.ascontiguousarray(self.texture, dtype=np.uint8)
            if tex.ndim != 3 or tex.shape[2] not in (3, 4) or 0 in tex.shape:
                raise ValueError(f"Material.texture must be uint8[H, W, 3|4], got {tex.shape}")
            object.__setattr__(self, "texture", _read_only(tex))


@dataclass(frozen=True, eq=False)
class RenderMesh:
    """A triangle mesh in its own object frame (metres, +Y up). Immutable: renderers cache its
    GPU buffers by identity. positions float32[V, 3]; normals float32[V, 3] (any length; zero
    means ambient only); uvs float32[V, 2] or None (required when a material has a texture);
    faces int32[F, 3]; face_material int32[F], index into materials; materials tuple[Material, ...]."""

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray | None
    faces: np.ndarray
    face_material: np.ndarray
    materials: tuple[Material, ...]

    def __post_init__(self) -> None:
        def coerce(name: str, dtype: type, shape: tuple[int | None, ...]) -> np.ndarray:
            a = np.ascontiguousarray(getattr(self, name), dtype=dtype)
            if a.ndim != len(shape) or any(want not in (None, got) for want, got in zip(shape, a.shape)):
                raise ValueError(f"RenderMesh.{name} has shape {a.shape}, expected {shape}")
            object.__setattr__(self, name, _read_only(a))
            return a

        n_vert = len(coerce("positions", np.float32, (None, 3)))
        coerce("normals", np.float32, (n_vert, 3))
        if self.uvs is not None:
            coerce("uvs", np.float32, (n_vert, 2))
        coerce("face_material", np.int32, (len(coerce("faces", np.int32, (None, 3))),))
        object.__setattr__(self, "materials", tuple(self.materials))
        if self.uvs is None and any(m.texture is not None for m in self.materials):
            raise ValueError("RenderMesh has a textured material but no uvs")
        for name, n in (("faces", n_vert), ("face_material", len(self.materials))):
            index = getattr(self, name)
            if index.size and (index.min() < 0 or index.max() >= n):
                raise ValueError(f"RenderMesh.{name} has an index outside [0, {n})")

    @property
    def bounds(self) -> np.ndarray:
        """float64[2, 3]: min and max corner of the positions, object frame."""
        return np.stack([self.positions.min(axis=0), self.positions.max(axis=0)]).astype(np.float64)

    @staticmethod
    def concatenate(meshes: Sequence[RenderMesh]) -> RenderMesh:
        """One mesh holding all of ``meshes`` (materials appended, not merged)."""
        if not meshes:
            raise ValueError("nothing to concatenate")
        vert_offsets = np.cumsum([0] + [len(m.positions) for m in meshes])
        mat_offsets = np.cumsum([0] + [len(m.materials) for m in meshes])
        uvs = [m.uvs if m.uvs is not None else np.zeros((len(m.positions), 2), np.float32) for m in meshes]
        return RenderMesh(
            positions=np.concatenate([m.positions for m in meshes]),
            normals=np.concatenate([m.normals for m in meshes]),
            uvs=np.concatenate(uvs) if any(m.uvs is not None for m in meshes) else None,
            faces=np.concatenate([m.faces + o for m, o in zip(meshes, vert_offsets)]),
            face_material=np.concatenate([m.face_material + o for m, o in zip(meshes, mat_offsets)]),
            materials=sum((m.materials for m in meshes), ()))

    @staticmethod
    def from_trimesh(obj: trimesh.Trimesh | trimesh.Scene) -> RenderMesh:
        """Convert a trimesh mesh or scene (scene-graph transforms baked in; non-mesh geometry
        skipped). Normals are smoothed across edges flatter than :data:`CREASE_ANGLE` only.
        Textures: SimpleMaterial.image (used alone: OBJ's Kd is often a placeholder) or
        PBRMaterial.baseColorTexture (times baseColorFactor, as glTF says). Colours: material
        diffuse / baseColorFactor, or face colours, or vertex colours averaged per face; one
        material per distinct colour."""
        if isinstance(obj, trimesh.Trimesh):
            return _convert_trimesh(obj, np.eye(4))
        parts = []
        for node in obj.graph.nodes_geometry:
            transform, name = obj.graph[node]
            if isinstance(geom := obj.geometry[name], trimesh.Trimesh) and len(geom.faces):
                parts.append(_convert_trimesh(geom, transform))
        if not parts:
            raise ValueError("the scene holds no triangle mesh")
        return RenderMesh.concatenate(parts)


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view: meshes are immutable because renderers cache their GPU copies."""
    view = a.view()
    view.flags.writeable = False
    return view


def _convert_trimesh(mesh: trimesh.Trimesh, transform: np.ndarray) -> RenderMesh:
    """One output vertex per group of face corners that share a vertex and a smooth edge chain."""
    faces, vertices = np.asarray(mesh.faces, np.int64), np.asarray(mesh.vertices, np.float64)
    T = np.asarray(transform, np.float64)
    smooth = mesh.face_adjacency_angles < CREASE_ANGLE
    pairs, edges = mesh.face_adjacency[smooth], mesh.face_adjacency_edges[smooth]
    # Corner ids (3 * face + slot) at both ends of every smooth edge, on both of its faces.
    a, b = (np.concatenate([3 * pairs[:, side] + np.argmax(faces[pairs[:, side]] == edges[:, [end]], axis=1)
                            for end in (0, 1)]) for side in (0, 1))
    n = 3 * len(faces)
    n_groups, labels = connected_components(coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n)),
                                            directed=False)
    vertex_of = np.empty(n_groups, np.int64)
    vertex_of[labels] = faces.ravel()
    tri = vertices[faces]
    area_normals = np.repeat(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), 3, axis=0)
    normals = np.stack([np.bincount(labels, area_normals[:, k], n_groups) for k in range(3)], axis=1)
    normals = normals @ _cofactor(T[:3, :3]).T
    materials, face_material, uvs = _trimesh_materials(mesh)
    return RenderMesh(positions=vertices[vertex_of] @ T[:3, :3].T + T[:3, 3],
                      normals=normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300),
                      uvs=None if uvs is None else uvs[vertex_of], faces=labels.reshape(-1, 3),
                      face_material=face_material, materials=materials)


def _trimesh_materials(mesh: trimesh.Trimesh) -> tuple[tuple[Material, ...], np.ndarray, np.ndarray | None]:
    """Materials, face_material int32[F] and per-vertex uvs float32[V, 2] (or None) of a trimesh mesh."""
    visual, zeros = mesh.visual, np.zeros(len(mesh.faces), np.int32)
    if isinstance(visual, trimesh.visual.TextureVisuals):
        mat, uv = visual.material, visual.uv
        pbr = isinstance(mat, trimesh.visual.material.PBRMaterial)
        image = mat.baseColorTexture if pbr else getattr(mat, "image", None)
        textured = image is not None and uv is not None and len(uv) == len(mesh.vertices)
        if pbr:  # glTF: the factor (default white) multiplies the texture
            factor = mat.baseColorFactor
            color = np.ones(4) if factor is None else trimesh.visual.color.to_rgba(factor) / 255.0
        else:  # OBJ: the texture alone, as Kd beside map_Kd is often a placeholder
            color = np.ones(4) if textured else np.asarray(mat.main_color) / 255.0
        if not textured:
            return (Material(color),), zeros, None
        rgba = "A" in image.getbands() or "transparency" in image.info
        texture = np.asarray(image.convert("RGBA" if rgba else "RGB"))
        return (Material(color, texture),), zeros, np.asarray(uv, np.float32)
    if not visual.defined:
        return (Material(),), zeros, None
    if visual.kind == "vertex":
        colors = np.round(np.asarray(visual.vertex_colors, np.float64)[mesh.faces].mean(axis=1))
    else:
        colors = np.asarray(visual.face_colors)
    unique, inverse = np.unique(colors.astype(np.uint8), axis=0, return_inverse=True)
    return tuple(Material(c / 255.0) for c in unique), inverse.reshape(-1).astype(np.int32), None


def _cofactor(A: np.ndarray) -> np.ndarray:
    """float64[3, 3] cofactor matrix det(A)·inv(A)^T: maps normals like the inverse-transpose up to
    a scale (normalised away later), and exists for singular A too."""
    c0, c1, c2 = A[:, 0], A[:, 1], A[:, 2]
    return np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)


def object_to_world(translation: Sequence[float], rotation_wxyz: Sequence[float],
                    scale: Sequence[float], mirrored: bool) -> np.ndarray:
    """float64[4, 4] ``T · R · S · diag(-1, 1, 1)`` (the last factor only when ``mirrored``): the
    official CAD-Estate object-to-world order, mirror => scale => rotation => translation."""
    M = np.eye(4)
    M[:3, :3] = quaternion_to_matrix(np.asarray(rotation_wxyz, np.float64)) * np.asarray(scale, np.float64)
    if mirrored:
        M[:3, 0] *= -1.0
    M[:3, 3] = translation
    return M


@dataclass(frozen=True, eq=False)
class Instance:
    """``mesh`` placed by ``object_to_world`` float64[4, 4] (object -> world, e.g. from
    :func:`object_to_world`); ``instance_id`` int in [0, MAX_INSTANCE_ID] labels its pixels."""

    mesh: RenderMesh
    object_to_world: np.ndarray
    instance_id: int

    def __post_init__(self) -> None:
        M = np.asarray(self.object_to_world, np.float64)
        if M.shape != (4, 4):
            raise ValueError(f"Instance.object_to_world must be 4x4, got {M.shape}")
        if not 0 <= self.instance_id <= MAX_INSTANCE_ID:
            raise ValueError(f"instance_id must be in [0, {MAX_INSTANCE_ID}], got {self.instance_id}")
        object.__setattr__(self, "object_to_world", M)


@dataclass(frozen=True, eq=False)
class Camera:
    """OpenCV pinhole camera. K float64[3, 3] pixel intrinsics; R float64[3, 3], t float64[3]
    world -> camera (``X_cam = R X_world + t``); image width x height pixels; near and far clip
    planes along camera z, metres."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    near: float = 0.05
    far: float = 100.0

    def view_matrix(self) -> np.ndarray:
        """float64[4, 4] world -> camera."""
        V = np.eye(4)
        V[:3, :3], V[:3, 3] = self.R, self.t
        return V

    def projection_matrix(self, supersample: int = 1) -> np.ndarray:
        """float64[4, 4] camera frame -> GL clip space of a framebuffer ``supersample`` times the
        image size. GL window x, y equal pixel u, v (times supersample), so GL's row 0 is image
        row 0 and framebuffer reads come out top row first; z maps [near, far] to [-1, 1]."""
        K = np.diag([supersample, supersample, 1.0]) @ np.asarray(self.K, np.float64)
        W, H, n, f = supersample * self.width, supersample * self.height, self.near, self.far
        return np.array([[2 * K[0, 0] / W, 2 * K[0, 1] / W, 2 * K[0, 2] / W - 1, 0],
                         [0, 2 * K[1, 1] / H, 2 * K[1, 2] / H - 1, 0],
                         [0, 0, (f + n) / (f - n), -2 * f * n / (f - n)],
                         [0, 0, 1, 0]])


@dataclass(frozen=True)
class Lighting:
    """Lambert + ambient: colour = albedo · (ambient + diffuse · |n · l|), clipped to 1.
    direction: world vector toward the light (any length)."""

    direction: tuple[float, float, float] = (0.3, 1.0, 0.5)
    ambient: float = 0.45
    diffuse: float = 0.65


@dataclass(frozen=True, eq=False)
class RenderResult:
    """rgb uint8[H, W, 3]; depth float32[H, W] camera-frame z in metres, inf on background;
    instance_id int32[H, W], -1 on background. Row 0 is the top of the image."""

    rgb: np.ndarray
    depth: np.ndarray
    instance_id: np.ndarray


_VERTEX_SHADER = """#version 330 core
uniform mat4 u_mvp;
uniform vec4 u_zrow;  // row 2 of (world->camera · object->world): camera z
uniform mat3 u_normal;
in vec3 in_position, in_normal;
in vec2 in_uv;
out vec3 v_normal; out vec2 v_uv; out float v_z;
void main() {
    gl_Position = u_mvp * vec4(in_position, 1.0);
    v_z = dot(u_zrow, vec4(in_position, 1.0));
    v_normal = u_normal * in_normal;
    v_uv = in_uv;
}"""

_FRAGMENT_SHADER = """#version 330 core
uniform sampler2D u_texture; uniform bool u_textured; uniform vec4 u_color;
uniform vec3 u_light; uniform float u_ambient, u_diffuse, u_id;
in vec3 v_normal; in vec2 v_uv; in float v_z;
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec2 f_data;  // (instance id, camera z)
void main() {
    vec4 albedo = u_textured ? u_color * texture(u_texture, v_uv) : u_color;
    if (albedo.a < 0.5) discard;
    float len = length(v_normal);
    float cosine = len > 0.0 ? abs(dot(v_normal / len, u_light)) : 0.0;
    f_color = vec4(min(albedo.rgb * (u_ambient + u_diffuse * cosine), 1.0), 1.0);
    f_data = vec2(u_id, v_z);
}"""


class _GpuPart(NamedTuple):
    """One material's faces: indices [first, first + count) of the mesh's index buffer."""
    first: int
    count: int
    color: tuple[float, ...]
    texture: moderngl.Texture | None


class _GpuMesh(NamedTuple):
    vao: moderngl.VertexArray
    parts: list[_GpuPart]
    buffers: tuple[moderngl.Buffer, moderngl.Buffer]  # vertices, indices: held to live as long


def _create_context() -> moderngl.Context:
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as exc:
        missing = ["lib" + name for name in ("EGL", "GL") if ctypes.util.find_library(name) is None]
        hint = (f"missing libraries: {', '.join(missing)} (Debian/Ubuntu: apt-get install libegl1 libgl1 "
                "libgl1-mesa-dri)" if missing else
                "libEGL and libGL are present; is a Mesa EGL driver installed (libegl-mesa0, libgl1-mesa-dri)?")
        raise RuntimeError(f"cannot create a headless EGL OpenGL context ({exc}); {hint}") from exc
    if ctx.version_code < 330:
        ctx.release()
        raise RuntimeError(f"OpenGL 3.3 needed, the EGL context offers {ctx.version_code}")
    return ctx


class Renderer:
    """Renders :class:`Instance` lists seen by a :class:`Camera` of the renderer's size.
    ``supersample`` s > 1 renders RGB at s times the size and box-filters it down; depth and ids
    always come from a pass at the output size, so they stay pixel-exact."""

    def __init__(self, width: int, height: int, supersample: int = 1) -> None:
        if width <= 0 or height <= 0 or supersample < 1:
            raise ValueError(f"bad renderer size {width}x{height}, supersample {supersample}")
        self.width, self.height, self.supersample = width, height, supersample
        self._ctx = ctx = _create_context()
        # Dropped GL objects queue up for ctx.gc(), run while this context is current: deleting
        # them whenever Python collects them would hit whichever context is current then.
        ctx.gc_mode = "context_gc"
        self._program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self._program["u_texture"].value = 0
        self._meshes: weakref.WeakKeyDictionary[RenderMesh, _GpuMesh] = weakref.WeakKeyDictionary()
        size, big = (width, height), (supersample * width, supersample * height)
        data = ctx.renderbuffer(size, components=2, dtype="f4")  # (instance id, camera z)
        self._fbo = ctx.framebuffer([ctx.renderbuffer(size, 4), data], ctx.depth_renderbuffer(size))
        self._data_fbo = ctx.framebuffer([data])  # to clear the data to (-1, inf) alone
        self._fbo_big = (ctx.framebuffer([ctx.renderbuffer(big, 4)], ctx.depth_renderbuffer(big))
                         if supersample > 1 else None)

    @property
    def cached_meshes(self) -> int:
        """How many meshes have buffers on the GPU."""
        return len(self._meshes)

    def render(self, instances: Sequence[Instance], camera: Camera, lighting: Lighting = Lighting(),
               background: Sequence[float] = (0.8, 0.8, 0.8)) -> RenderResult:
        """Rasterise ``instances``; see :class:`RenderResult`. ``background``: RGB in [0, 1]."""
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"camera is {camera.width}x{camera.height}, renderer {self.width}x{self.height}")
        if not 0 < camera.near < camera.far:
            raise ValueError(f"need 0 < near < far, got {camera.near}, {camera.far}")
        light = np.asarray(lighting.direction, np.float64)
        bg = (*(float(c) for c in background), 1.0)
        with self._ctx:  # several renderers may share a thread: make ours current
            self._ctx.gc()
            self._program["u_light"].value = tuple(light / np.linalg.norm(light))
            self._program["u_ambient"].value = lighting.ambient
            self._program["u_diffuse"].value = lighting.diffuse
            self._ctx.enable_only(moderngl.DEPTH_TEST)
            if self._fbo_big is not None:
                self._draw(self._fbo_big, instances, camera, self.supersample, bg)
            self._draw(self._fbo, instances, camera, 1, bg)
            data = np.frombuffer(self._fbo.read(attachment=1, components=2, dtype="f4"), np.float32)
            rgb = self._read_rgb()
        data = data.reshape(self.height, self.width, 2)
        return RenderResult(rgb, np.ascontiguousarray(data[..., 1]), data[..., 0].astype(np.int32))

    def _draw(self, fbo: moderngl.Framebuffer, instances: Sequence[Instance], camera: Camera,
              supersample: int, background: tuple[float, ...]) -> None:
        fbo.use()
        fbo.clear(*background, depth=1.0)
        if fbo is self._fbo:
            self._data_fbo.clear(-1.0, np.inf)
            fbo.use()
        prog, view = self._program, camera.view_matrix()
        proj_view = camera.projection_matrix(supersample) @ view
        for inst in instances:
            if not len(inst.mesh.faces):
                continue
            gpu, M = self._upload(inst.mesh), inst.object_to_world
            prog["u_mvp"].write((proj_view @ M).T.astype(np.float32).tobytes())
            prog["u_zrow"].value = tuple((view @ M)[2])
            prog["u_normal"].write(_cofactor(M[:3, :3]).T.astype(np.float32).tobytes())
            prog["u_id"].value = float(inst.instance_id)
            for part in gpu.parts:
                prog["u_color"].value = part.color
                prog["u_textured"].value = part.texture is not None
                if part.texture is not None:
                    part.texture.use(0)
                gpu.vao.render(moderngl.TRIANGLES, vertices=part.count, first=part.first)

    def _read_rgb(self) -> np.ndarray:
        s, H, W = self.supersample, self.height, self.width
        if self._fbo_big is None:
            return np.frombuffer(self._fbo.read(components=3), np.uint8).reshape(H, W, 3)
        big = np.frombuffer(self._fbo_big.read(components=3), np.uint8).reshape(H, s, W, s, 3)
        total = np.full((H, W, 3), s * s // 2, np.uint32)  # rounds the mean to nearest
        for i in range(s):
            for j in range(s):
                total += big[:, i, :, j]  # strided slices: far faster than sum(axis=(1, 3))
        return (total // (s * s)).astype(np.uint8)

    def _upload(self, mesh: RenderMesh) -> _GpuMesh:
        if (gpu := self._meshes.get(mesh)) is not None:
            return gpu
        uvs = mesh.uvs if mesh.uvs is not None else np.zeros((len(mesh.positions), 2), np.float32)
        vbo = self._ctx.buffer(np.hstack([mesh.positions, mesh.normals, uvs]).astype(np.float32).tobytes())
        ibo = self._ctx.buffer(mesh.faces[np.argsort(mesh.face_material, kind="stable")].astype(np.uint32).tobytes())
        vao = self._ctx.vertex_array(self._program, [(vbo, "3f 3f 2f", "in_position", "in_normal", "in_uv")],
                                     index_buffer=ibo, index_element_size=4)
        counts = np.bincount(mesh.face_material, minlength=len(mesh.materials))
        firsts = np.cumsum(counts) - counts
        parts = [_GpuPart(3 * int(first), 3 * int(count), tuple(float(c) for c in mat.color),
                          None if mat.texture is None else self._upload_texture(mat.texture))
                 for mat, first, count in zip(mesh.materials, firsts, counts) if count]
        gpu = self._meshes[mesh] = _GpuMesh(vao, parts, (vbo, ibo))
        return gpu

    def _upload_texture(self, image: np.ndarray) -> moderngl.Texture:
        h, w, channels = image.shape
        # Rows flipped: GL's texture row 0 is v = 0, the bottom of the image.
        tex = self._ctx.texture((w, h), channels, np.ascontiguousarray(image[::-1]).tobytes(), alignment=1)
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        return tex

    def release(self) -> None:
        """Free the GL context and everything on the GPU; the renderer is unusable afterwards."""
        self._meshes.clear()
        self._ctx.release()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
