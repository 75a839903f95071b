"""cadestate.render: projection matches geometry.project, official pose convention, depth/ids,
textures and shading, trimesh conversion, GPU buffer cache (and a printed timing)."""

import gc
import time

import numpy as np
import pytest
import trimesh
from PIL import Image

from cadestate.geometry import look_at, project, quaternion_to_matrix
from cadestate.render import (
    Camera, Instance, Lighting, Material, Renderer, RenderMesh, object_to_world,
)

W, H = 640, 360
K = np.array([[520.0, 0.0, 317.3], [0.0, 505.0, 181.6], [0.0, 0.0, 1.0]])
FLAT = Lighting(ambient=1.0, diffuse=0.0)  # colour = albedo
BACKGROUND = 204  # the default background, 0.8, as uint8


@pytest.fixture(scope="module")
def renderer():
    with Renderer(W, H) as r:
        yield r


@pytest.fixture(scope="module")
def renderer_ss():
    with Renderer(W, H, supersample=2) as r:
        yield r


def quad(corners, material=Material((0.9, 0.6, 0.3)), uvs=None) -> RenderMesh:
    """Two triangles over 4 corners float[4, 3] given in order around the quad."""
    corners = np.asarray(corners, np.float64)
    n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    return RenderMesh(corners, np.tile(n / np.linalg.norm(n), (4, 1)), uvs, [[0, 1, 2], [0, 2, 3]],
                      [0, 0], (material,))


def coloured_box(extents, centre, rgba) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents)
    box.apply_translation(centre)
    box.visual.face_colors = rgba
    return box


def transform(M, points):
    return np.asarray(points) @ M[:3, :3].T + M[:3, 3]


def mask_box(mask):
    """Continuous pixel bounding box (umin, vmin, umax, vmax) of a boolean mask."""
    rows, cols = np.nonzero(mask)
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], np.float64)


def projected_box(camera, points):
    uv, depth = project(camera.K, camera.R, camera.t, points)
    assert (depth > camera.near).all()
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def pixel(uv):
    """(row, col) of the pixel holding image point uv."""
    return int(np.floor(uv[1])), int(np.floor(uv[0]))


def rotation_wxyz(axis, degrees):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return np.concatenate([[np.cos(half)], np.sin(half) * axis])


@pytest.mark.parametrize("which", ["renderer", "renderer_ss"])
def test_coverage_is_exactly_the_projected_polygon(which, request):
    """Pixel (i, j) is covered iff its centre (i+0.5, j+0.5) lies inside the quad's projection by
    geometry.project: a half-pixel or y-flip error would change whole rows and columns."""
    r = request.getfixturevalue(which)
    R, t = look_at([0.7, 1.4, 3.1], [0.1, 0.9, 0.0])
    camera = Camera(K, R, t, W, H)
    corners = np.array([[-0.8, -0.5, 0.0], [0.9, -0.6, 0.1], [0.7, 0.55, -0.2], [-0.6, 0.4, 0.0]])
    M = object_to_world([0.1, 0.95, -0.1], rotation_wxyz([0.2, 1.0, 0.1], 25), [1.1, 0.9, 1.0], False)
    res = r.render([Instance(quad(corners), M, 3)], camera)

    uv, _ = project(K, R, t, transform(M, corners))
    px, py = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    edges = np.roll(uv, -1, axis=0) - uv
    dist = np.stack([(e[0] * (py - c[1]) - e[1] * (px - c[0])) / np.linalg.norm(e) for c, e in zip(uv, edges)])
    nxt = np.roll(uv, -1, axis=0)
    dist *= np.sign((uv[:, 0] * nxt[:, 1] - nxt[:, 0] * uv[:, 1]).sum())  # inside > 0 for either winding
    inside = (dist > 0).all(axis=0)
    on_edge = np.abs(dist).min(axis=0) < 0.02
    mask = res.instance_id == 3
    assert inside.sum() > 20000
    assert not (mask != inside)[~on_edge].any()
    assert set(np.unique(res.instance_id)) == {-1, 3}
    interior = np.abs(dist).min(axis=0) > 1.0
    colours = np.unique(res.rgb[inside & interior], axis=0)
    assert len(colours) == 1  # flat quad: one shade inside
    if r.supersample > 1:  # anti-aliased edges: shades between the quad's and the background's
        edge = res.rgb[np.abs(dist).min(axis=0) < 0.3].astype(int)
        lo, hi = np.minimum(colours[0], BACKGROUND), np.maximum(colours[0], BACKGROUND)
        assert ((edge > lo + 5) & (edge < hi - 5)).any(axis=1).sum() > 50


MARKER = np.array([0.4, 0.3, 0.0])  # marker cube centre, object frame


def marked_bar() -> RenderMesh:
    """Asymmetric test object: a blue bar along x with a red marker cube at its +x end, on top."""
    bar = coloured_box([1.0, 0.4, 0.3], [0.0, 0.0, 0.0], [40, 60, 230, 255])
    marker = coloured_box([0.2, 0.2, 0.2], MARKER, [230, 30, 30, 255])
    return RenderMesh.from_trimesh(trimesh.util.concatenate([bar, marker]))


def red(rgb):
    return (rgb[..., 0].astype(int) > 2 * rgb[..., 2].astype(int))


def test_object_to_world_is_T_R_S_mirror():
    q, s, tr = rotation_wxyz([0.3, 1.0, -0.2], 40), np.array([1.3, 0.7, 1.1]), np.array([0.3, 0.8, -0.5])
    T = np.eye(4)
    T[:3, 3] = tr
    Rm = np.eye(4)
    Rm[:3, :3] = quaternion_to_matrix(q)
    S = np.diag([*s, 1.0])
    np.testing.assert_allclose(object_to_world(tr, q, s, False), T @ Rm @ S, atol=1e-12)
    np.testing.assert_allclose(object_to_world(tr, q, s, True), T @ Rm @ S @ np.diag([-1.0, 1, 1, 1]), atol=1e-12)


@pytest.mark.parametrize("mirrored", [False, True])
def test_official_pose_covers_projected_vertices_and_marker_side(renderer, mirrored):
    mesh = marked_bar()
    tr, q, s = [0.3, 0.8, -0.5], rotation_wxyz([0.3, 1.0, -0.2], 40), [1.3, 0.7, 1.1]
    M = object_to_world(tr, q, s, mirrored)
    R, t = look_at([1.5, 2.0, 3.0], tr)
    camera = Camera(K, R, t, W, H)
    res = renderer.render([Instance(mesh, M, 0)], camera)
    np.testing.assert_allclose(mask_box(res.instance_id == 0), projected_box(camera, transform(M, mesh.positions)),
                               atol=1.0)
    # The marker shows where the official transform puts it, not at the other end of the bar.
    here, _ = project(K, R, t, transform(M, [MARKER]))
    other, _ = project(K, R, t, transform(M, [MARKER * [-1, 1, 1]]))
    assert red(res.rgb)[pixel(here[0])] and not red(res.rgb)[pixel(other[0])]


def test_mirroring_equals_flipping_a_symmetric_view(renderer):
    """With a camera symmetric about the world x = 0 plane (cx = W/2) and a pose that commutes
    with diag(-1, 1, 1) (tx = 0, rotation about x, diagonal scale), mirroring the object flips
    the image left-right."""
    R, t = look_at([0.0, 1.2, 4.0], [0.0, 1.0, 0.0])
    camera = Camera(np.array([[500.0, 0, W / 2], [0, 500, 170.2], [0, 0, 1]]), R, t, W, H)
    pose = ([0.0, 0.9, 0.2], rotation_wxyz([1, 0, 0], 20), [1.2, 0.8, 1.0])
    mesh = marked_bar()
    plain, mirrored = (renderer.render([Instance(mesh, object_to_world(*pose, m), 1)], camera) for m in (False, True))
    a, b = plain.instance_id == 1, mirrored.instance_id == 1
    assert (a != b).sum() > 1000  # the object is not symmetric
    assert (np.fliplr(a) != b).sum() <= 10
    both = np.fliplr(a) & b
    np.testing.assert_allclose(np.fliplr(plain.depth)[both], mirrored.depth[both], atol=1e-4)


def test_depth_is_camera_z_and_nearer_instance_wins(renderer_ss):
    camera = Camera(K, np.eye(3), np.zeros(3), W, H)  # world = camera frame
    far = quad([[-1, -0.5, 3], [1, -0.5, 3], [1, 0.5, 3], [-1, 0.5, 3]])
    near = quad([[-0.3, -0.2, 2], [0.5, -0.2, 2], [0.5, 0.2, 2], [-0.3, 0.2, 2]])
    res = renderer_ss.render([Instance(far, np.eye(4), 7), Instance(near, np.eye(4), 123456)], camera)
    assert res.depth.dtype == np.float32 and res.instance_id.dtype == np.int32
    assert res.depth.shape == res.instance_id.shape == (H, W) and res.rgb.shape == (H, W, 3)
    np.testing.assert_allclose(res.depth[res.instance_id == 7], 3.0, atol=1e-3)
    np.testing.assert_allclose(res.depth[res.instance_id == 123456], 2.0, atol=1e-3)
    centre, _ = project(K, np.eye(3), np.zeros(3), [[0.1, 0.0, 2.0]])
    assert res.instance_id[pixel(centre[0])] == 123456
    assert res.instance_id[0, 0] == -1 and np.isinf(res.depth[0, 0])
    assert ((res.instance_id == -1) == np.isinf(res.depth)).all()
    assert (res.rgb[0, 0] == BACKGROUND).all()


def test_depth_of_a_tilted_plane(renderer):
    """Depth is the camera z of the plane along each pixel-centre ray, not a GL depth value."""
    R, t = look_at([0.4, 1.5, 2.0], [0.0, 0.5, -1.0])
    camera = Camera(K, R, t, W, H)
    corners = np.array([[-3, 0, -4], [3, 0, -4], [3, 0.8, 1], [-3, 0.8, 1]], np.float64)  # a slope
    res = renderer.render([Instance(quad(corners), np.eye(4), 0)], camera)
    rows, cols = np.nonzero(res.instance_id == 0)
    rays = np.stack([cols + 0.5, rows + 0.5, np.ones_like(cols, float)], axis=1) @ np.linalg.inv(K).T
    p0 = R @ corners[0] + t
    n = np.cross(R @ (corners[1] - corners[0]), R @ (corners[3] - corners[0]))
    z = (n @ p0) / (rays @ n)  # rays have z = 1, so the ray parameter is the camera z
    assert len(z) > 10000
    np.testing.assert_allclose(res.depth[rows, cols], z, rtol=2e-4)


def fronto_camera():
    """Camera at the origin looking down world -z: image right = +x, image up = +y."""
    R, t = look_at([0.0, 0.0, 0.0], [0.0, 0.0, -1.0])
    return Camera(K, R, t, W, H)


def screen_quad(material, x0=1.0, y0=0.6, z=-2.0):
    """Quad facing the fronto camera; uv (0, 0) at its bottom-left corner, (1, 1) top-right."""
    corners = [[-x0, -y0, z], [x0, -y0, z], [x0, y0, z], [-x0, y0, z]]
    return quad(corners, material, uvs=[[0, 0], [1, 0], [1, 1], [0, 1]]), np.asarray(corners)


def cell_centres(rows, cols, corners):
    """World centres of texture cells (row 0 = top of the texture) on a screen_quad."""
    (x0, y0, z) = corners[0]
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    u, v = (c + 0.5) / cols, 1 - (r + 0.5) / rows
    return np.stack([x0 + u * (-2 * x0), y0 + v * (-2 * y0), np.full(u.shape, z)], axis=-1).reshape(-1, 3)


@pytest.mark.parametrize("channels", [3, 4])
def test_texture_cells_land_where_expected(renderer_ss, channels):
    rng = np.random.default_rng(1)
    texture = rng.integers(0, 256, size=(3, 5, channels), dtype=np.uint8)  # not a power of two
    if channels == 4:
        texture[..., 3] = 255
        texture[1, 2, 3] = 0  # a hole
    mesh, corners = screen_quad(Material((1, 1, 1), texture))
    camera = fronto_camera()
    res = renderer_ss.render([Instance(mesh, np.eye(4), 2)], camera, FLAT)
    uv, _ = project(camera.K, camera.R, camera.t, cell_centres(3, 5, corners))
    for (row, col), (u, v) in zip(np.ndindex(3, 5), uv):
        if channels == 4 and (row, col) == (1, 2):
            assert res.instance_id[pixel((u, v))] == -1 and np.isinf(res.depth[pixel((u, v))])
        else:
            np.testing.assert_allclose(res.rgb[pixel((u, v))], texture[row, col, :3], atol=2)


def test_colour_is_lambert_plus_ambient_with_mirrored_anisotropic_pose(renderer):
    colour, light = np.array([0.8, 0.3, 0.2]), Lighting(direction=(0.3, 1.0, 0.5), ambient=0.3, diffuse=0.6)
    a, b = np.array([1, -1, 0]) / np.sqrt(8), np.array([1, 1, -2]) / np.sqrt(24)
    corners = np.array([-a - b, a - b, a + b, b - a])  # normal along (1, 1, 1)
    M = object_to_world([0.1, -0.1, -2.5], rotation_wxyz([1.0, 0.5, 0.0], 50), [2.0, 0.5, 1.5], True)
    camera = fronto_camera()
    res = renderer.render([Instance(quad(corners, Material(colour)), M, 0)], camera, light)
    l_world = np.asarray(light.direction) / np.linalg.norm(light.direction)
    n_world = np.linalg.inv(M[:3, :3]).T @ [1, 1, 1]
    n_naive = M[:3, :3] @ [1, 1, 1]
    shade = lambda n: 0.3 + 0.6 * abs(n @ l_world) / np.linalg.norm(n)  # noqa: E731
    assert abs(shade(n_world) - shade(n_naive)) > 0.05  # the pose makes the normal transform matter
    centre, _ = project(camera.K, camera.R, camera.t, transform(M, [[0.0, 0.0, 0.0]]))
    assert res.instance_id[pixel(centre[0])] == 0
    np.testing.assert_allclose(res.rgb[pixel(centre[0])], np.clip(colour * shade(n_world), 0, 1) * 255, atol=1.5)


def test_from_trimesh_box_with_face_colours(renderer):
    box = trimesh.creation.box([0.6, 1.0, 0.4])
    palette = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [0, 255, 255], [255, 0, 255]])
    normals = box.face_normals
    side = np.argmax(np.abs(normals), axis=1) * 2 + (normals.max(axis=1) > 0.5)
    box.visual.face_colors = np.hstack([palette[side], np.full((12, 1), 255)])
    mesh = RenderMesh.from_trimesh(box)
    assert len(mesh.materials) == 6 and len(mesh.faces) == 12
    np.testing.assert_allclose(mesh.bounds, box.bounds, atol=1e-6)
    # Face normals survive the conversion (the box's edges are creases).
    np.testing.assert_allclose(np.abs(mesh.normals).max(axis=1), 1.0, atol=1e-6)

    light = Lighting(direction=(0.3, 1.0, 0.5), ambient=0.4, diffuse=0.5)
    R, t = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])
    camera = Camera(K, R, t, W, H)
    res = renderer.render([Instance(mesh, np.eye(4), 4)], camera, light)
    np.testing.assert_allclose(mask_box(res.instance_id == 4), projected_box(camera, box.vertices), atol=1.0)
    front = palette[2 * 2 + 1] / 255.0  # the +z face
    shade = 0.4 + 0.5 * 0.5 / np.linalg.norm(light.direction)
    np.testing.assert_allclose(res.rgb[pixel(K[:2, 2])], np.clip(front * shade, 0, 1) * 255, atol=1.5)


def test_from_trimesh_scene_bakes_transforms(renderer):
    scene = trimesh.Scene()
    table = coloured_box([1.2, 0.05, 0.8], [0, 0, 0], [200, 150, 100, 255])
    scene.add_geometry(table, transform=trimesh.transformations.translation_matrix([0.3, 0.75, -0.2]))
    leg = trimesh.creation.cylinder(radius=0.05, height=0.7, sections=24)
    leg.visual.vertex_colors = [30, 90, 60, 255]
    pose = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])  # cylinder axis z -> y
    pose[:3, 3] = [-0.2, 0.35, 0.1]
    scene.add_geometry(leg, transform=pose)
    mesh = RenderMesh.from_trimesh(scene)
    np.testing.assert_allclose(mesh.bounds, scene.bounds, atol=1e-6)
    colours = sorted(tuple(np.round(m.color * 255)) for m in mesh.materials)
    assert colours == [(30, 90, 60, 255), (200, 150, 100, 255)]
    # The cylinder's side is smooth (normals off the face normals), its caps flat.
    assert len(mesh.positions) < 3 * len(mesh.faces)

    R, t = look_at([1.5, 1.6, 2.2], [0.0, 0.5, 0.0])
    camera = Camera(K, R, t, W, H)
    M = object_to_world([0.2, 0.0, -0.3], rotation_wxyz([0, 1, 0], 30), [1.0, 1.0, 1.0], False)
    res = renderer.render([Instance(mesh, M, 9)], camera)
    world = transform(M, scene.to_mesh().vertices)
    np.testing.assert_allclose(mask_box(res.instance_id == 9), projected_box(camera, world), atol=1.0)


@pytest.mark.parametrize("kind", ["simple", "pbr"])
def test_from_trimesh_keeps_textures(renderer, kind):
    texture = np.zeros((2, 2, 3), np.uint8)
    texture[0, 0], texture[0, 1], texture[1, 0], texture[1, 1] = [250, 0, 0], [0, 250, 0], [0, 0, 250], [250, 250, 0]
    image = Image.fromarray(texture)
    material = (trimesh.visual.material.SimpleMaterial(image=image, diffuse=[100, 100, 100, 255]) if kind == "simple"
                else trimesh.visual.material.PBRMaterial(baseColorTexture=image, baseColorFactor=[255, 255, 255, 255]))
    corners = np.array([[-1.0, -0.6, -2], [1.0, -0.6, -2], [1.0, 0.6, -2], [-1.0, 0.6, -2]])
    tm = trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False,
                         visual=trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], material=material))
    mesh = RenderMesh.from_trimesh(tm)
    np.testing.assert_array_equal(mesh.materials[0].texture, texture)
    camera = fronto_camera()
    res = renderer.render([Instance(mesh, np.eye(4), 0)], camera, FLAT)
    uv, _ = project(camera.K, camera.R, camera.t, cell_centres(2, 2, corners))
    for (row, col), point in zip(np.ndindex(2, 2), uv):
        np.testing.assert_allclose(res.rgb[pixel(point)], texture[row, col], atol=2)


def test_gpu_buffers_are_uploaded_once_and_freed_with_the_mesh(renderer):
    camera = fronto_camera()
    mesh, _ = screen_quad(Material((0.2, 0.4, 0.6)))
    assert not mesh.positions.flags.writeable  # immutable, so the GPU copy stays valid
    before = renderer.cached_meshes
    first = renderer.render([Instance(mesh, np.eye(4), 0), Instance(mesh, np.eye(4), 1)], camera)
    assert renderer.cached_meshes == before + 1
    again = renderer.render([Instance(mesh, np.eye(4), 0)], camera)
    assert renderer.cached_meshes == before + 1
    np.testing.assert_array_equal(first.rgb, again.rgb)
    other, _ = screen_quad(Material((0.2, 0.4, 0.6)), z=-3.0)
    renderer.render([Instance(other, np.eye(4), 0)], camera)
    assert renderer.cached_meshes == before + 2
    del mesh, other, first, again
    gc.collect()
    assert renderer.cached_meshes == before


def test_renderers_sharing_a_thread_keep_their_own_context(renderer):
    """Each render makes its own context current, and GL objects dropped by one renderer are
    deleted in that renderer's context, never in another's."""
    camera = fronto_camera()
    mesh, _ = screen_quad(Material((0.2, 0.4, 0.6)))
    expected = renderer.render([Instance(mesh, np.eye(4), 5)], camera)
    other = Renderer(W, H)  # creating it makes its context current
    other.render([Instance(screen_quad(Material((1, 0, 0)), z=-1.0)[0], np.eye(4), 6)], camera)
    same = lambda res: (res.rgb == expected.rgb).all() and (res.instance_id == expected.instance_id).all()  # noqa: E731
    assert same(renderer.render([Instance(mesh, np.eye(4), 5)], camera))
    other.release()
    newer = Renderer(W, H)  # current now; GL object names restart, so they clash with other's
    del other
    gc.collect()  # other's GL objects are dropped while newer's context is current
    assert same(newer.render([Instance(mesh, np.eye(4), 5)], camera))
    assert same(renderer.render([Instance(mesh, np.eye(4), 5)], camera))
    newer.release()


def test_camera_size_must_match(renderer):
    with pytest.raises(ValueError, match="camera is"):
        renderer.render([], Camera(K, np.eye(3), np.zeros(3), 320, 180))


def test_timing_ten_objects(capsys):
    """Print ms per 640x360 frame of 10 objects of ~10k faces (informative, not asserted)."""
    rng = np.random.default_rng(0)
    meshes = [RenderMesh.from_trimesh(trimesh.creation.uv_sphere(0.4, count=[36, 72])) for _ in range(10)]
    places = [[x, y, -3.0 + 0.5 * y] for y in (0.3, 1.3) for x in np.linspace(-1.8, 1.8, 5)]
    instances = [Instance(m, object_to_world(p, rotation_wxyz(rng.normal(size=3), 30), rng.uniform(0.6, 1.1, 3),
                                             False), i) for i, (m, p) in enumerate(zip(meshes, places))]
    R, t = look_at([0.0, 1.5, 2.0], [0.0, 0.8, -2.5])
    camera = Camera(K, R, t, W, H)
    lines = [f"{len(meshes[0].faces)} faces per object"]
    for s in (1, 2):
        with Renderer(W, H, supersample=s) as r:
            res = r.render(instances, camera)
            start = time.perf_counter()
            for _ in range(10):
                r.render(instances, camera)
            lines.append(f"supersample={s}: {(time.perf_counter() - start) * 100:.1f} ms/frame")
        assert set(np.unique(res.instance_id)) == {-1, *range(10)}
    with capsys.disabled():
        print("\nrender timing, 640x360, 10 objects:", "; ".join(lines))
