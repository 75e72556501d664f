"""Image and model files from untrusted sources: decoded fully, refused with a ValueError
naming the file when corrupt, and never able to end the process.

Panda3D's own readers exit the interpreter (status 1, no exception) on a truncated BMP,
PPM or TGA texture, also when an .egg model references one, and accept a truncated JPEG.
The cases that could do that run in a child process here, so that a crash fails the test
instead of ending pytest.
"""
import json
import math
import os
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np
import pytest
import torch
from PIL import Image

import marl_render as mr
from marl_render.images import load_image, texture_pixels

FORMATS = {"bmp": "BMP", "ppm": "PPM", "tga": "TGA", "jpg": "JPEG", "png": "PNG"}

QUAD_EGG = """<CoordinateSystem> { Z-up }
%(texture)s
<VertexPool> quad {
  <Vertex> 0 { -0.5 0 -0.5 <UV> { 0 0 } }
  <Vertex> 1 { 0.5 0 -0.5 <UV> { 1 0 } }
  <Vertex> 2 { 0.5 0 0.5 <UV> { 1 1 } }
  <Vertex> 3 { -0.5 0 0.5 <UV> { 0 1 } }
}
<Group> quad_group {
  %(transform)s
  <Polygon> { %(tref)s <VertexRef> { 0 1 2 3 <Ref> { quad } } }
}
"""


def quad_egg(path, texture=None, transform=""):
    """A unit quad in the XZ plane facing -Y (counter-clockwise seen from -Y), without normals."""
    path.write_text(QUAD_EGG % {"texture": f"<Texture> tex {{ {texture} }}" if texture else "",
                                "tref": "<TRef> { tex }" if texture else "", "transform": transform})
    return path


def pixels(seed=0, shape=(12, 16, 3)):
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """A valid file and one cut to half its length for every format: {ext: (good, truncated)}."""
    folder = tmp_path_factory.mktemp("images")
    files = {}
    for ext, pil_format in FORMATS.items():
        good = folder / f"good.{ext}"
        Image.fromarray(pixels()).save(good, format=pil_format)
        data = good.read_bytes()
        cut = folder / f"truncated.{ext}"
        cut.write_bytes(data[: len(data) // 2])
        files[ext] = (good, cut)
    return files


# Runs in a child process: each case prints one JSON line with the outcome, and the child
# renders a frame at the end to show that it is still alive.
CHILD = textwrap.dedent("""
    import json, sys
    import marl_render as mr
    from marl_render.panda_buffers import panda_texture

    def attempt(case, call):
        try:
            call()
            outcome = {"case": case, "error": None}
        except Exception as error:
            outcome = {"case": case, "error": type(error).__name__, "message": str(error)}
        print(json.dumps(outcome), flush=True)

    def scene():
        return mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("texture",))

    for path in json.loads(sys.argv[1]):
        attempt(["add_group texture", path], lambda: scene().add_group("quads", "box", capacity=1, texture=path))
        attempt(["add_static texture", path], lambda: scene().add_static("floor", "plane", [0, 0, 0], texture=path))
        attempt(["renderer texture", path], lambda: panda_texture(path, "quads"))
    for path in json.loads(sys.argv[2]):
        attempt(["model", path], lambda: scene().add_group("quads", path, capacity=1))
    renderer = mr.BatchRenderer(scene())
    print(json.dumps({"alive": list(renderer.render().rgb.shape)}), flush=True)
""")


def run_child(textures, models):
    child = subprocess.run([sys.executable, "-c", CHILD, json.dumps([str(p) for p in textures]),
                            json.dumps([str(p) for p in models])], capture_output=True, text=True, timeout=600)
    lines = [json.loads(line) for line in child.stdout.splitlines() if line.startswith("{")]
    assert child.returncode == 0 and lines and "alive" in lines[-1], (
        f"the process died (exit status {child.returncode}) after {lines}:\n{child.stderr[-2000:]}")
    assert lines[-1]["alive"] == [1, 1, 8, 8, 3]
    return {tuple(line["case"]): line for line in lines[:-1]}


def test_truncated_texture_files_raise_a_value_error_naming_the_file(images):
    truncated = [cut for _, cut in images.values()]
    outcomes = run_child(truncated, [])
    assert len(outcomes) == 3 * len(truncated)
    for (case, path), outcome in outcomes.items():
        assert outcome["error"] == "ValueError", (case, path, outcome)
        assert f"image file {path!r} could not be decoded" in outcome["message"], (case, outcome)
        assert "truncated" in outcome["message"].lower(), (case, outcome)


def test_a_model_referencing_a_truncated_texture_raises_naming_both_files(images, tmp_path):
    models = [quad_egg(tmp_path / f"uses_{ext}.egg", cut) for ext, (_, cut) in images.items()]
    outcomes = run_child([], models)
    assert len(outcomes) == len(models)
    for model, (_, cut) in zip(models, images.values(), strict=True):
        outcome = outcomes[("model", str(model))]
        assert outcome["error"] == "ValueError", outcome
        assert f"mesh: model file {str(model)!r} references the texture {str(cut)!r}, which is not a complete image" \
            in outcome["message"], outcome


def test_a_bam_model_referencing_a_truncated_texture_raises_naming_it(images, tmp_path):
    """The check does not depend on the model format: a .bam file names its textures too."""
    good, cut = images["bmp"]
    texture = tmp_path / "skin.bmp"
    texture.write_bytes(good.read_bytes())
    egg, bam = quad_egg(tmp_path / "quad.egg", texture), tmp_path / "quad.bam"
    convert = ("import sys; from panda3d.core import Loader, NodePath, Filename; "
               "NodePath(Loader.get_global_ptr().load_sync(Filename.from_os_specific(sys.argv[1])))"
               ".write_bam_file(Filename.from_os_specific(sys.argv[2]))")
    subprocess.run([sys.executable, "-c", convert, str(egg), str(bam)], check=True, capture_output=True, timeout=120)
    assert mr.load_model(bam).triangles.shape == (2, 3)  # loads while its texture is whole
    texture.write_bytes(cut.read_bytes())
    outcome = run_child([], [bam])[("model", str(bam))]
    assert outcome["error"] == "ValueError"
    assert f"references the texture {str(texture)!r}, which is not a complete image" in outcome["message"]


@pytest.mark.parametrize("ext", ["png", "bmp", "ppm", "tga"])
def test_valid_image_files_decode_to_their_exact_pixels(images, ext):
    good, _ = images[ext]
    decoded = load_image(good)
    assert decoded.dtype == np.uint8 and decoded.shape == (12, 16, 3)
    assert np.array_equal(decoded, pixels())
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("texture",))
    assert np.array_equal(scene.add_group("quads", "box", capacity=1, texture=good).texture, pixels())


def test_images_with_alpha_or_a_palette_or_grey_levels_decode_to_rgb_or_rgba(tmp_path):
    rgba = pixels(1, (4, 5, 4))
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    assert np.array_equal(load_image(tmp_path / "rgba.png"), rgba)
    grey = pixels(2, (4, 5, 1))[..., 0]
    Image.fromarray(grey, "L").save(tmp_path / "grey.png")
    assert np.array_equal(load_image(tmp_path / "grey.png"), np.repeat(grey[..., None], 3, axis=2))
    palette = Image.fromarray(grey, "L").convert("P")
    palette.info["transparency"] = int(np.asarray(palette)[0, 0])
    palette.save(tmp_path / "palette.png", transparency=palette.info["transparency"])
    decoded = load_image(tmp_path / "palette.png")
    assert decoded.shape == (4, 5, 4) and decoded[0, 0, 3] == 0 and np.array_equal(decoded[..., 0], grey)


def test_a_textured_model_file_renders_with_the_group_texture(images, tmp_path):
    """Model textures are checked but never shown: the group's own texture is what is drawn."""
    good, _ = images["png"]
    model = quad_egg(tmp_path / "quad.egg", good)
    texture = np.zeros((2, 2, 3), dtype=np.uint8)
    texture[...] = (255, 0, 255)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(20, 20), effects=("texture",), background=(0, 0, 0))
    scene.add_group("quads", str(model), capacity=1, texture=texture)
    with mr.BatchRenderer(scene) as renderer:
        renderer.set_cameras(position=torch.zeros(1, 1, 3), rotation=torch.tensor([[[1.0, 0, 0, 0]]]))
        renderer.update("quads", position=[[[0, 2, 0]]], active=[[True]], color=[[[1.0, 1.0, 1.0]]])
        rgb = renderer.render().rgb
    assert rgb[0, 0, 10, 10].tolist() == [255, 0, 255]
    assert rgb[0, 0, 0, 0].tolist() == [0, 0, 0]


def test_a_model_without_normals_gets_the_normals_of_its_faces(tmp_path):
    quad = mr.load_model(quad_egg(tmp_path / "plain.egg"))
    assert quad.positions.shape == (4, 3) and quad.triangles.shape == (2, 3)
    assert np.allclose(sorted(map(tuple, quad.positions)),
                       [(-0.5, 0, -0.5), (-0.5, 0, 0.5), (0.5, 0, -0.5), (0.5, 0, 0.5)])
    assert np.allclose(quad.normals, [0, -1, 0])  # counter-clockwise seen from -Y


def bam_of_a_plane(path, **transform):
    """mr.plane() (facing +Z) under two nodes, the inner one with `transform`, saved as .bam."""
    from panda3d.core import NodePath

    from marl_render.meshes import to_panda_geom

    root = NodePath("root")
    outer = root.attach_new_node("outer")
    outer.set_pos(0, 0, 3)
    inner = outer.attach_new_node(to_panda_geom(mr.plane()))
    for name, value in transform.items():
        getattr(inner, f"set_{name}")(*value)
    assert root.write_bam_file(str(path))
    return path


def test_model_triangles_carry_every_node_transform(tmp_path):
    plane = mr.plane()
    moved = mr.load_model(bam_of_a_plane(tmp_path / "moved.bam", scale=(2,), hpr=(90, 0, 0)))
    turn = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])  # heading 90 degrees: +X to +Y
    assert np.allclose(moved.positions, (2 * plane.positions) @ turn.T + [0, 0, 3], atol=1e-6)
    assert np.allclose(moved.normals, [0, 0, 1], atol=1e-6) and np.array_equal(moved.triangles, plane.triangles)
    mirrored = mr.load_model(bam_of_a_plane(tmp_path / "mirrored.bam", scale=(1, 1, -1)))
    assert np.allclose(mirrored.normals, [0, 0, -1])
    corners = mirrored.positions[mirrored.triangles]
    facing = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (facing[:, 2] < 0).all(), "a mirrored model must keep its faces counter-clockwise seen from outside"


@pytest.mark.parametrize("make,error,message", [
    (lambda tmp: tmp, ValueError, r"mesh must be a regular model file, got '.*', which is a directory"),
    (lambda tmp: "/dev/null", ValueError,
     r"mesh must be a regular model file, got '/dev/null', which is a character device"),
    (lambda tmp: tmp / "missing.egg", FileNotFoundError, r"mesh: model file '.*missing.egg' does not exist"),
    (lambda tmp: (tmp / "notes.txt", (tmp / "notes.txt").write_text("hello"))[0], ValueError,
     r"mesh: model file '.*notes.txt' is not a model file: Panda3D has no loader for its extension '.txt'"),
    (lambda tmp: (tmp / "empty.egg", (tmp / "empty.egg").write_text(""))[0], ValueError,
     r"mesh: model file '.*empty.egg' contains no triangles"),
    (lambda tmp: b"/tmp/x.egg", TypeError, r"mesh must be a MeshData, a procedural name .* got b'/tmp/x.egg'"),
])
def test_bad_model_paths_raise_naming_the_argument(tmp_path, make, error, message):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    with pytest.raises(error, match=message):
        scene.add_group("model", make(tmp_path), capacity=1)
    assert not scene.groups and not scene.static


def test_model_paths_may_be_path_objects(tmp_path):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    group = scene.add_group("model", quad_egg(tmp_path / "quad.egg"), capacity=1)
    assert group.mesh.name == "quad.egg" and group.mesh.triangles.shape == (2, 3)


@pytest.mark.parametrize("make,error,message", [
    (lambda tmp: tmp, ValueError, r"texture must be a regular image file, got '.*', which is a directory"),
    (lambda tmp: "/dev/zero", ValueError,
     r"texture must be a regular image file, got '/dev/zero', which is a character device"),
    (lambda tmp: tmp / "missing.png", FileNotFoundError, r"texture: image file '.*missing.png' does not exist"),
    (lambda tmp: (tmp / "notes.png", (tmp / "notes.png").write_text("hello"))[0], ValueError,
     r"texture: image file '.*notes.png' could not be decoded: UnidentifiedImageError"),
    (lambda tmp: np.zeros((0, 4, 3), np.uint8), ValueError,
     r"texture must be a uint8 array \[h, w, 3\|4\] with h, w >= 1"),
    (lambda tmp: np.zeros((4, 4), np.uint8), ValueError, r"texture must be a uint8 array \[h, w, 3\|4\]"),
    (lambda tmp: np.zeros((4, 4, 3), np.float32), ValueError, r"texture must be a uint8 array .*dtype float32"),
    (lambda tmp: [[[0, 0, 0]]], TypeError, r"texture must be an image file path or a uint8 array"),
])
def test_bad_textures_raise_naming_the_argument_when_the_group_is_added(tmp_path, make, error, message):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("texture",))
    with pytest.raises(error, match=message):
        scene.add_group("boxes", "box", capacity=1, texture=make(tmp_path))
    with pytest.raises(error, match=message):
        scene.add_static("floor", "plane", [0, 0, 0], texture=make(tmp_path))
    assert not scene.groups and not scene.static


def test_a_texture_array_is_copied_when_the_group_is_added():
    texture = pixels()
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("texture",))
    group = scene.add_group("boxes", "box", capacity=1, texture=texture)
    texture[...] = 0
    assert np.array_equal(group.texture, pixels())
    assert np.array_equal(texture_pixels(torch.from_numpy(pixels())), pixels())


def test_mesh_data_checks_its_arrays():
    box = mr.box()
    with pytest.raises(TypeError, match=r"mesh 'm': positions must be a numpy array of floating dtype, got list"):
        mr.MeshData("m", box.positions.tolist(), box.normals, box.uvs, box.triangles)
    with pytest.raises(TypeError,
                       match=r"mesh 'm': triangles must be a numpy array of integer dtype, got array of dtype float32"):
        mr.MeshData("m", box.positions, box.normals, box.uvs, box.triangles.astype(np.float32))
    positions = box.positions.copy()
    positions[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"mesh 'm': positions must be finite"):
        mr.MeshData("m", positions, box.normals, box.uvs, box.triangles)


# ---------------------------------------------------------------------- the loader's child process
def test_the_loader_child_does_not_run_code_from_the_working_directory(tmp_path):
    """The child was started with `python -c`, so the working directory came first on its module
    path: a numpy.py planted where the user runs a script was executed."""
    model = quad_egg(tmp_path / "quad.egg")
    work = tmp_path / "work"
    work.mkdir()
    marker = tmp_path / "planted_ran"
    (work / "numpy.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\nraise ImportError('planted')\n")
    script = tmp_path / "scripts" / "load.py"  # a user's script, run from the folder with the planted module
    script.parent.mkdir()
    script.write_text(f"import marl_render as mr\nprint(mr.load_model({str(model)!r}).triangles.shape)")
    run = subprocess.run([sys.executable, str(script)], cwd=work, capture_output=True, text=True, timeout=120)
    assert not marker.exists(), run.stderr
    assert "(2, 3)" in run.stdout, run.stderr


def test_model_files_that_would_hang_the_parser_are_refused_at_once(tmp_path, monkeypatch):
    cycle = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
             "nodes": [{"name": "root", "children": [1]}, {"name": "j1", "children": [2]},
                       {"name": "j2", "children": [1]}]}
    (tmp_path / "cycle.gltf").write_text(json.dumps(cycle))
    (tmp_path / "self.gltf").write_text(json.dumps({**cycle, "nodes": [{"name": "me", "children": [0]}]}))
    (tmp_path / "zero.egg").write_text('<CoordinateSystem> { Z-up }\n<Texture> tex { "/dev/zero" }\n')
    corners = 10_001
    (tmp_path / "face.obj").write_text("".join(f"v {math.cos(i)} {math.sin(i)} 0\n" for i in range(corners))
                                       + "f " + " ".join(str(i + 1) for i in range(corners)) + "\n")
    cases = [("cycle.gltf", r"cycle in its node hierarchy \(node 1 \('j1'\) -> node 2 \('j2'\) -> node 1"),
             ("self.gltf", r"cycle in its node hierarchy \(node 0 \('me'\) -> node 0"),
             ("zero.egg", r"references '/dev/zero', which is not a regular file"),
             ("face.obj", r"a face with 10001 corners on line 10002")]
    def parser_started(*args, **kwargs):
        raise AssertionError(f"the parser's child process was started: {args}")

    # "At once" is "before the parser starts" (whatever the machine's speed): no child process is run.
    monkeypatch.setattr(subprocess, "run", parser_started)
    for file, words in cases:
        with pytest.raises(ValueError, match=words):
            mr.load_model(tmp_path / file)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="timeout must be a finite number > 0, got 0.0"):
        mr.load_model(quad_egg(tmp_path / "quad.egg"), timeout=0)


@pytest.mark.parametrize("parent_alive", [True, False])
def test_a_child_whose_parent_died_before_it_started_watching_exits_at_once(tmp_path, parent_alive):
    """The child asks to be killed with its parent as it starts; a parent killed before that (a
    loaded machine) left it parsing on: it checks that its parent is still the one that started it.
    A wrong parent pid stands for the parent that died (the child would have been reparented)."""
    from marl_render import meshes

    output = tmp_path / "arrays.npz"
    parent = os.getpid() if parent_alive else 1
    done = subprocess.run([sys.executable, "-I", "-c", meshes._CHILD_BOOTSTRAP, meshes.__file__,
                           str(quad_egg(tmp_path / "quad.egg")), str(output), "_write_model_arrays", str(parent),
                           os.pathsep.join(sys.path)],
                          capture_output=True, timeout=120, cwd=tmp_path)
    assert (done.returncode, output.exists()) == ((0, True) if parent_alive else (3, False)), done.stderr[-2000:]


def test_a_killed_parent_leaves_no_parser_and_no_work_folder(tmp_path):
    """A parent killed during a load used to leave the child spinning and its temporary files behind."""
    import psutil

    corners = 9_000  # a few seconds of triangulation: the load is under way when the parent is killed
    model = tmp_path / "slow.obj"
    model.write_text("".join(f"v {math.cos(i * 0.001)} {math.sin(i * 0.001)} 0\n" for i in range(corners))
                     + "f " + " ".join(str(i + 1) for i in range(corners)) + "\n")
    parent = subprocess.Popen([sys.executable, "-c", f"import marl_render as mr; mr.load_model({str(model)!r})"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        children = []
        while not children and time.monotonic() < deadline:
            children = psutil.Process(parent.pid).children()
            time.sleep(0.05)
        assert children, "the load never started its child"
        folders = [f for f in os.listdir(tempfile.gettempdir()) if f.startswith(f"marl_render_model_{parent.pid}_")]
        assert folders
        parent.kill()
        parent.wait(timeout=10)
        gone, alive = psutil.wait_procs(children, timeout=60)  # at once, normally: a bound for a hang, not a speed
        assert not alive
    finally:
        if parent.poll() is None:
            parent.kill()
    mr.load_model(quad_egg(tmp_path / "quad.egg"))  # the next load removes the dead process's folder
    assert not any(f.startswith(f"marl_render_model_{parent.pid}_") for f in os.listdir(tempfile.gettempdir()))


def test_an_unusable_interpreter_is_named_not_the_model_file(tmp_path, monkeypatch):
    model = quad_egg(tmp_path / "quad.egg")
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no_such_python"))
    with pytest.raises(RuntimeError, match=r"the Python interpreter '.*no_such_python' \(sys.executable\) could not "
                                           r"be started"):
        mr.load_model(model)
    base = getattr(sys, "_base_executable", None)  # outside the venv: no numpy, no panda3d
    probe = subprocess.run([base, "-I", "-c", "import numpy, panda3d"], capture_output=True) if base else None
    if probe is None or probe.returncode == 0:
        pytest.skip("no interpreter without numpy / panda3d at hand")
    monkeypatch.setattr(sys, "executable", base)
    # the child also gets the parent's sys.path: without the venv's packages there, as a parent would be
    monkeypatch.setattr(sys, "path", [p for p in sys.path if "site-packages" not in p])
    with pytest.raises(RuntimeError, match=r"(numpy|panda3d) cannot be imported by .*install it for that interpreter"):
        mr.load_model(model)


def test_the_model_parser_imports_what_its_parent_imports(tmp_path):
    """The parser child runs isolated (-I), which drops PYTHONPATH: an install that lives only there
    (the GPU kit's `pip install --target`) found no panda3d in the child. Here a bare interpreter
    reaches every package through sys.path entries that the parent added itself."""
    import venv

    bare = tmp_path / "bare"
    venv.EnvBuilder(with_pip=False).create(bare)
    code = ("import site, sys; [site.addsitedir(p) for p in sys.argv[1:]]\n"
            "from marl_render.meshes import parse_model_file\n"
            f"path, arrays = parse_model_file({str(quad_egg(tmp_path / 'quad.egg'))!r}, 'model', skinned=False)\n"
            "print(len(arrays['triangles']))")
    sites = [p for p in sys.path if p.endswith("site-packages")]
    done = subprocess.run([str(bare / "bin" / "python"), "-c", code, *sites], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["2"]
