"""Contract test suites: what every sensor, simulator, generator, scene and object source (in-tree or from a
plugin) must satisfy.

Subclass a suite in a test module and name the component; pytest collects the inherited tests::

    from tnf.testing import SensorContract

    class TestGelSightContract(SensorContract):
        name = "gelsight"

Each suite has class attributes a subclass may set (``params``: config overrides, e.g. to make a generator
tiny) and fixtures it may override (``sensor``, ``simulator``, ``generator``, ``scene``, ``source``) when a
component needs more than its registry name to be built. The tests use real components: real warp presses,
real training steps, real renders, at tiny sizes so that a suite runs in seconds on a CPU.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import textwrap
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.cameras import look_at
from tnf.errors import TnfError
from tnf.objects import REFUSE_SIZE, ObjectSource
from tnf.registry import (
    GENERATORS,
    OBJECTS,
    SCENES,
    SENSORS,
    SIMULATORS,
    Registry,
    config_to_dict,
    defaults_source,
    split_spec,
)
from tnf.scenes import load_scene, save_scene
from tnf.sensors import Sensor
from tnf.sim.base import Simulator
from tnf.testing.config import compose


def undocumented_fields(config_class: type) -> list[str]:
    """Fields of a Config dataclass (and its dataclass bases) without a docstring right below them."""
    missing = []
    for klass in config_class.__mro__:
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):  # no source (e.g. built dynamically): nothing to check
            continue
        body = tree.body[0].body  # type: ignore[attr-defined]
        for stmt, nxt in zip(body, body[1:] + [None]):
            if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
                doc = isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                if not (doc and isinstance(nxt.value.value, str)):  # type: ignore[union-attr]
                    missing.append(f"{klass.__qualname__}.{stmt.target.id}")
    return missing


class _ComponentContract:
    """Checks shared by every kind: registration, documentation and the config round trip."""

    registry: ClassVar[Registry]
    name: ClassVar[str]
    """Registry name of the component under test."""
    params: ClassVar[dict[str, Any]] = {}
    """Config overrides used to build it (keep tests tiny)."""

    @classmethod
    def spec(cls) -> dict[str, Any]:
        """``{"name": name, **params}``: the config node the component is built from."""
        return {"name": cls.name, **cls.params}

    def test_registered_with_description(self):
        entry = self.registry.entry(self.name)
        doc = (entry.obj.__doc__ or "").strip()
        assert doc, f"{entry.obj.__qualname__} needs a docstring: its first line is what `tnf list` shows"
        assert dataclasses.is_dataclass(entry.config_class), "the component must declare a nested Config dataclass"

    def test_config_fields_documented(self):
        missing = undocumented_fields(self.registry.entry(self.name).config_class)
        assert not missing, f"Config fields need a docstring below them (units): {missing}"

    def test_config_round_trip(self):
        cfg = self.registry.config(self.name, self.params)
        data = config_to_dict(cfg)
        assert json.loads(json.dumps(data)) == data, "config_to_dict must give plain JSON data"
        again = self.registry.config(self.name, data)
        assert config_to_dict(again) == data
        for k, v in self.params.items():
            assert _close(data[k], v), f"override {k}={v!r} did not reach the config ({data[k]!r})"

    def test_unknown_key_is_an_error_naming_it(self):
        with pytest.raises(TnfError, match="no_such_key"):
            self.registry.config(self.name, {**self.params, "no_such_key": 1})

    def test_config_defaults_are_its_yaml(self):
        """The Config takes its defaults from the option named like the component (``conf/<kind>/<name>.yaml``,
        through ``@yaml_defaults``), so that ``<kind>=<name>`` on the command line and ``build("<name>")`` in code
        agree, and each default is written once."""
        from hydra.errors import MissingConfigException

        group = self.registry.kind  # the config group has the registry's kind as its name
        try:
            node = compose("touch", [f"{group}={self.name}"])[group]
        except MissingConfigException:
            pytest.skip(f"no conf/{group}/{self.name}.yaml: {self.name} is built in code only")
        cls = self.registry.entry(self.name).config_class
        source = defaults_source(cls)
        assert source is not None and Path(source).parts[-2:] == (group, f"{self.name}.yaml"), (
            f"{cls.__qualname__} takes its defaults from {source}: decorate it with "
            f'@yaml_defaults("{group}/{self.name}", conf=<your package\'s conf folder>) under @dataclass'
        )
        _, params = split_spec(node)
        assert config_to_dict(cls()) == params, f"{group}={self.name} composes other values than {source} holds"


def _close(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, float) or isinstance(b, float):
        return bool(np.isclose(a, b))
    return bool(a == b)


# -- sensors ----------------------------------------------------------------------------------------
class SensorContract(_ComponentContract):
    """A tactile sensor (``tnf.sensors.Sensor`` subclass) works with the config tree and the warp simulator.

    Checks: registration and documented Config fields; config round trip through the registry and
    ``config_to_dict``; the sensor's YAML (``conf/sensor/<name>.yaml``, or a plugin's through ``tnf.conf``)
    composes and builds; camera, gel and shading outputs have the documented shapes and dtypes; the
    background is ``[H, W, 3]`` uint8, the same for the same seed and different for another; a sphere pressed
    with the ``warp_gel`` simulator makes contact and an image that differs from the background, and a press
    that misses leaves the background (plus noise); a mirror symmetry the sensor reports holds in the simulator.
    """

    registry = SENSORS
    simulator: ClassVar[dict[str, Any]] = {"name": "warp_gel"}
    """Simulator config used for the press test."""
    sphere_radius: ClassVar[float] = 0.01
    """Radius of the pressed sphere, metres."""

    @pytest.fixture(scope="class")
    @classmethod
    def sensor(cls) -> Any:
        """The sensor under test (built once per test class)."""
        return SENSORS.build(cls.spec())

    @classmethod
    def press_force(cls, sensor: Any) -> float:
        """Target force of the press test, newtons: a tenth of the way into the sensor's force range."""
        lo, hi = sensor.cfg.force_range
        return float(lo + 0.1 * (hi - lo))

    def test_is_a_sensor_named_as_registered(self, sensor):

        assert isinstance(sensor, Sensor)
        assert sensor.name == self.name, "set the class attribute `name` to the registry name"
        assert sensor.describe() == {"name": self.name, "config": config_to_dict(sensor.cfg)}

    def test_yaml_composes_and_builds(self):
        cfg = compose("touch", [f"sensor={self.name}"])
        built = SENSORS.build(cfg.sensor)
        assert built.name == self.name

    def test_camera_and_gel_shapes(self, sensor):
        h, w = sensor.height, sensor.width
        fx, fy, cx, cy = sensor.intrinsics()
        assert fx > 0 and fy > 0 and 0 < cx < w and 0 < cy < h
        x, y = sensor.gel_grid()
        assert x.shape == y.shape == (h, w) and x.dtype == y.dtype == np.float32
        assert x[0, 0] < x[0, -1] and y[0, 0] > y[-1, 0], "columns grow with +x, rows with -y"
        surf = sensor.gel_surface()
        assert surf.shape == (h, w) and surf.dtype == np.float32
        assert np.isfinite(surf).all() and surf.min() >= 0
        mask = sensor.gel_mask()
        assert mask.shape == (h, w) and mask.dtype == bool and mask.mean() > 0.25
        pts = sensor.gel_points()
        assert pts.shape == (h, w, 3) and pts.dtype == np.float32 and (pts[..., 2] < 0).all()
        n = sensor.surface_normals(surf)
        assert n.shape == (h, w, 3) and np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-4) and (n[..., 2] > 0).all()
        lit = sensor.shade(pts, n)
        assert lit.shape == (h, w, 3) and lit.dtype == np.float32 and np.isfinite(lit).all() and lit.min() >= 0

    def test_background_shape_dtype_determinism(self, sensor):
        bg = sensor.background()
        assert bg.shape == (sensor.height, sensor.width, 3) and bg.dtype == np.uint8
        assert np.array_equal(bg, sensor.background()), "the background must be deterministic"
        assert 10 < bg.mean() < 245, "a background should be neither black nor white"
        if sensor.cfg.background_image or sensor.cfg.calibration:
            return  # a photo does not vary with the seed
        b0, b1 = sensor.background(0), sensor.background(1)
        assert np.array_equal(b0, sensor.background(0))
        assert np.abs(b0.astype(np.int16) - b1).mean() > 1, "another seed should give another background"

    @pytest.fixture(scope="class")
    @classmethod
    def pressed(cls, sensor) -> tuple[Any, Any, float]:
        """``(simulator, TouchBatch, target force)`` of three presses on a sphere (the third one misses)."""
        import trimesh

        r = cls.sphere_radius
        sim = SIMULATORS.build(cls.simulator, sensor=sensor, device="cpu")
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=r)
        # Camera above the sphere looking down (-z): centred, off-centre by a third of the sphere's radius,
        # and one beside the sphere that misses it.
        poses = np.repeat(np.eye(4)[None], 3, 0)
        poses[:, 2, 3] = r + sensor.cfg.camera_distance + 0.01
        poses[1, 0, 3] = r / 3
        poses[2, 0, 3] = 10 * r
        force = cls.press_force(sensor)
        return sim, sim.press(sphere, poses, force, seed=0), force

    def test_press_on_sphere_makes_contact(self, sensor, pressed):
        _, out, force = pressed
        h, w = sensor.height, sensor.width
        assert out.images.shape == (3, h, w, 3) and out.images.dtype == np.uint8
        assert out.indentation.shape == (3, h, w) and out.indentation.dtype == np.float32
        assert out.contact.shape == (3, h, w) and out.contact.dtype == bool
        assert out.hit.tolist() == [True, True, False]
        for i in (0, 1):
            assert out.contact[i].any() and out.indentation[i].max() > 0
            assert 0 < out.force[i] <= force * 1.05
            assert 0 < out.penetration[i] <= sensor.cfg.max_penetration * 1.001
        assert not out.contact[2].any()

    def test_press_changes_the_image_and_a_miss_does_not(self, sensor, pressed):
        _, out, _ = pressed
        bg = sensor.background().astype(np.float32)
        for i in (0, 1):
            diff = np.abs(out.images[i].astype(np.float32) - bg).mean(-1)
            assert diff[out.contact[i]].mean() > 8, "the contact should show in the image"
        miss = np.abs(out.images[2].astype(np.float32) - bg)
        assert miss.mean() < 3 * max(sensor.cfg.noise_std, 1.0), "no contact should give the background plus noise"

    def test_mirror_symmetry_holds_in_the_simulator(self, sensor, pressed):
        """Where ``mirror_channels`` reports a symmetry (``data.augment=[mirror]`` relies on it), the press
        off-centre by +r/3 is the press at -r/3 flipped left-right with its channels reordered."""
        order = sensor.mirror_channels()
        if order is None:
            pytest.skip(f"{self.name} has no mirror symmetry")
        import trimesh

        sim, out, force = pressed
        r = self.sphere_radius
        pose = np.eye(4)
        pose[2, 3] = r + sensor.cfg.camera_distance + 0.01
        pose[0, 3] = -r / 3
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=r)
        mirrored = sim.press(sphere, pose[None], force, seed=1)
        bg = sensor.background().astype(np.float32)
        diff = out.images[1].astype(np.float32) - bg
        diff_m = mirrored.images[0].astype(np.float32) - bg
        region = out.contact[1][:, ::-1] | mirrored.contact[0]
        energy = np.abs(diff_m)[region].mean()
        err = np.abs(diff[:, ::-1][..., list(order)] - diff_m)[region].mean()
        assert err < 0.1 * energy + 2 * sensor.cfg.noise_std, (
            f"mirror_channels() says {order}, but the mirrored press differs by {err:.1f} (imprint {energy:.1f})"
        )


# -- generators -------------------------------------------------------------------------------------
def random_batch(batch_size: int = 2, size: int = 128, seed: int = 0) -> dict[str, Any]:
    """A batch of conditions and targets as ``tnf.data`` yields them: float32 in [-1, 1], ``object_id`` long."""
    import torch

    g = torch.Generator().manual_seed(seed)

    def img(c: int) -> torch.Tensor:
        return torch.rand(batch_size, c, size, size, generator=g) * 2 - 1

    return {
        "rgb": img(3),
        "depth": img(1),
        "background": img(3),
        "tactile": img(3),
        "object_id": torch.arange(batch_size, dtype=torch.long),
    }


class GeneratorContract(_ComponentContract):
    """A generator (``tnf.generators.Generator`` subclass) builds from its name, generates, trains and saves.

    Checks: registration and documented Config; config round trip; built from its registry name it is a
    ``Generator``; ``generate`` on a batch of ``batch_size`` gives ``[B, 3, 128, 128]`` in [-1, 1]; one
    ``training_step`` returns finite losses and changes the weights; a Lightning checkpoint stores the
    registry name and config (no class paths: it loads with ``weights_only=True``) and loads back.
    Set ``params`` to make the networks tiny.
    """

    registry = GENERATORS
    batch_size: ClassVar[int] = 2
    image_size: ClassVar[int] = 128

    @pytest.fixture
    def generator(self) -> Any:
        import torch

        torch.manual_seed(0)
        return GENERATORS.build(self.spec())

    def test_is_a_generator(self, generator):
        from tnf.generators import Generator

        assert isinstance(generator, Generator)
        from tnf.generators.nets.conditioning import CHANNELS

        # Batch keys tnf serves, or conditions derived from them (depth_slope, depth_and_slope).
        assert generator.inputs and set(generator.inputs) <= set(CHANNELS)

    def test_generate_shape_and_range(self, generator):
        import torch

        generator.eval()
        with torch.no_grad():
            out = generator.generate(random_batch(self.batch_size, self.image_size))
        assert out.shape == (self.batch_size, 3, self.image_size, self.image_size)
        assert out.dtype == torch.float32 and torch.isfinite(out).all()
        assert out.min() >= -1 and out.max() <= 1

    def test_one_training_step(self, generator):
        import torch

        from tnf.generators import PlainOptimisation

        generator.train()
        before = {k: v.detach().clone() for k, v in generator.named_parameters()}
        losses = generator.training_step(random_batch(self.batch_size, self.image_size), PlainOptimisation(generator))
        assert losses and all(torch.isfinite(v).all() and v.numel() == 1 for v in losses.values()), losses
        changed = [k for k, v in generator.named_parameters() if not torch.equal(v, before[k])]
        assert changed, "a training step must update some weights"

    @pytest.mark.filterwarnings("ignore:.*validation_step.*:UserWarning")
    def test_checkpoint_stores_name_not_class_path(self, tmp_path):
        import lightning as L
        import torch

        from tnf.generators import GeneratorSystem, load_generator
        from tnf.generators.system import read_checkpoint

        system = GeneratorSystem(self.spec(), epochs=1, decay_epochs=0, grid_rows=0)
        loader = torch.utils.data.DataLoader([_unbatch(random_batch(1, self.image_size, s)) for s in range(2)], 2)
        # No steps: the training step has its own test; this one is about what a checkpoint stores.
        trainer = L.Trainer(
            max_steps=0,
            accelerator="cpu",
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            limit_val_batches=0,
            default_root_dir=tmp_path,
        )
        trainer.fit(system, loader)
        path = tmp_path / "last.ckpt"
        trainer.save_checkpoint(path)
        ckpt = read_checkpoint(path)  # loads with weights_only=True: no pickled classes inside
        assert ckpt["tnf"]["generator"]["name"] == self.name
        module = type(system.generator).__module__
        text = json.dumps({k: v for k, v in ckpt.items() if k in ("tnf", "hyper_parameters")}, default=str)
        assert module not in text, f"the checkpoint names a class path ({module})"
        loaded = load_generator(path, expected=self.name)
        for k, v in system.state_dict().items():
            assert torch.equal(v.cpu(), loaded.state_dict()[k].cpu()), k


def _unbatch(batch: dict[str, Any]) -> dict[str, Any]:
    return {k: v[0] for k, v in batch.items()}


# -- scenes -----------------------------------------------------------------------------------------
class SceneContract(_ComponentContract):
    """A scene (``tnf.scenes.base.Scene``) renders RGB-D with the documented shapes and ranges.

    Checks: registration and documented Config; config round trip; ``render_rgbd`` for B cameras looking at
    the origin gives rgb ``[B, H, W, 3]`` in [0, 1], depth ``[B, H, W]`` >= 0 and opacity ``[B, H, W]`` in
    [0, 1], all finite float32; ``intrinsics`` may be ``[4]`` or ``[B, 4]``; a registered scene saves and
    loads back by name (``save_scene`` / ``load_scene``) and renders the same. Override the ``scene`` fixture
    for a scene that needs more than its config (e.g. a mesh); set ``params`` to make it tiny.
    """

    registry = SCENES
    width: ClassVar[int] = 16
    height: ClassVar[int] = 12
    distance: ClassVar[float] = 0.3
    """Camera distance from the origin, metres (scenes are objects of a few centimetres at the origin)."""
    saveable: ClassVar[bool] = True
    """Whether ``save_scene`` / ``load_scene`` apply (false for scenes built from data they do not store)."""

    @pytest.fixture
    def scene(self) -> Any:
        import torch

        torch.manual_seed(0)
        return SCENES.build(self.spec()).eval()

    def cameras(self, batch: int = 2) -> tuple[Any, Any]:
        """``c2w [B, 4, 4]`` looking at the origin from around it, and intrinsics ``[4]`` (45 degree vertical fov)."""
        import torch

        eyes = [(self.distance, 0.0, 0.05), (0.0, -self.distance, 0.1), (0.0, 0.0, self.distance)][:batch]
        c2w = torch.tensor(
            np.stack([look_at(np.array(e), np.zeros(3), fallback="parallel") for e in eyes]), dtype=torch.float32
        )
        f = 0.5 * self.height / np.tan(np.radians(22.5))
        return c2w, torch.tensor([f, f, self.width / 2, self.height / 2], dtype=torch.float32)

    def _check(self, out: Any, batch: int) -> None:
        import torch

        h, w = self.height, self.width
        assert set(out) >= {"rgb", "depth", "opacity"}
        assert out["rgb"].shape == (batch, h, w, 3)
        assert out["depth"].shape == out["opacity"].shape == (batch, h, w)
        for k in ("rgb", "depth", "opacity"):
            assert out[k].dtype == torch.float32 and torch.isfinite(out[k]).all(), k
        assert out["rgb"].min() >= 0 and out["rgb"].max() <= 1
        assert out["opacity"].min() >= 0 and out["opacity"].max() <= 1 + 1e-5
        assert out["depth"].min() >= 0

    def test_render_rgbd_shapes_and_ranges(self, scene):
        import torch

        c2w, k = self.cameras(2)
        with torch.no_grad():
            self._check(scene.render_rgbd(c2w, k, self.width, self.height), 2)
            self._check(scene.render_rgbd(c2w[:1], k[None], self.width, self.height, chunk=37), 1)

    def test_save_and_load_by_name(self, scene, tmp_path):
        import torch

        if not self.saveable:
            pytest.skip(f"{self.name} scenes are not saved as checkpoints")

        path = save_scene(scene, tmp_path)
        blob = torch.load(path, map_location="cpu", weights_only=True)
        assert blob["name"] == self.name
        loaded = load_scene(tmp_path)
        c2w, k = self.cameras(1)
        with torch.no_grad():
            a = scene.render_rgbd(c2w, k, self.width, self.height)
            b = loaded.render_rgbd(c2w, k, self.width, self.height)
        for key in ("rgb", "depth", "opacity"):
            assert torch.allclose(a[key], b[key], atol=1e-5), key


# -- simulators -------------------------------------------------------------------------------------
def sphere_gaps(sensor: Any, radius: float, centre_xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``[H, W]`` gaps (metres, along the sensor's -z) from the undeformed gel to a sphere of ``radius`` metres
    whose top touches the gel's lowest point; inf where the pixel's ray misses the sphere."""
    pts = sensor.gel_points().astype(np.float64)
    r2 = (pts[..., 0] - centre_xy[0]) ** 2 + (pts[..., 1] - centre_xy[1]) ** 2
    cz = pts[..., 2].min() - radius  # the sphere's top at the gel's lowest point
    top = cz + np.sqrt(np.maximum(radius**2 - r2, 0.0))
    gaps = np.where(r2 < radius**2, pts[..., 2] - top, np.inf)
    return (gaps - np.nanmin(gaps[np.isfinite(gaps)])).astype(np.float32)


class SimulatorContract(_ComponentContract):
    """A tactile simulator (``tnf.sim.base.Simulator`` subclass) presses a sensor and returns a ``TouchBatch``.

    Checks: registration and documented Config; config round trip; the YAML (``conf/simulator/<name>.yaml``,
    or a plugin's) composes and builds; the background is the sensor's ``[H, W, 3]`` uint8; three presses on a
    sphere (centred, off-centre, beside it) give every ``TouchBatch`` field with its shape and dtype, contact
    for the first two and none for the third (no contact point, no advance); the same seed gives the same
    images; a larger force goes deeper over a larger area; ``press_heights`` to a penetration indents that deep,
    and to a force reaches it; a penetration past the sensor's ``max_penetration`` is a one-line TnfError naming
    the setting.
    """

    registry = SIMULATORS
    sensor_spec: ClassVar[dict[str, Any]] = {"name": "digit", "width": 60, "height": 80}
    """The sensor the simulator is built for (small, to keep the suite fast)."""
    sphere_radius: ClassVar[float] = 0.01
    """Radius of the pressed sphere, metres."""

    @pytest.fixture(scope="class")
    @classmethod
    def simulator(cls) -> Any:
        """The simulator under test on the CPU (built once per test class)."""
        sensor = SENSORS.build(cls.sensor_spec)
        return SIMULATORS.build(cls.spec(), sensor=sensor, device="cpu")

    @classmethod
    def forces(cls, sensor: Any) -> tuple[float, float]:
        """A light and a firm press, newtons: a tenth and a third of the way into the sensor's force range."""
        lo, hi = sensor.cfg.force_range
        return float(lo + 0.1 * (hi - lo)), float(lo + 0.33 * (hi - lo))

    @classmethod
    def poses(cls, sensor: Any) -> np.ndarray:
        """``[3, 4, 4]`` start poses above the sphere looking down: centred, off-centre by r/3, and beside it."""
        r = cls.sphere_radius
        poses = np.repeat(np.eye(4)[None], 3, 0)
        poses[:, 2, 3] = r + sensor.cfg.camera_distance + 0.01
        poses[1, 0, 3] = r / 3
        poses[2, 0, 3] = 10 * r
        return poses

    @pytest.fixture(scope="class")
    @classmethod
    def pressed(cls, simulator) -> Any:
        """The ``TouchBatch`` of the three presses at the light force."""
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=cls.sphere_radius)
        return simulator.press(sphere, cls.poses(simulator.sensor), cls.forces(simulator.sensor)[0], seed=0)

    def test_is_a_simulator(self, simulator):

        assert isinstance(simulator, Simulator)
        s = simulator.sensor
        assert simulator.background.shape == (s.height, s.width, 3) and simulator.background.dtype == np.uint8

    def test_yaml_composes_and_builds(self):
        cfg = compose("touch", [f"simulator={self.name}"])
        assert cfg.simulator.name == self.name
        built = SIMULATORS.build(cfg.simulator, sensor=SENSORS.build(self.sensor_spec), device="cpu")
        assert type(built) is SIMULATORS.get(self.name)

    def test_touch_batch_fields(self, simulator, pressed):
        h, w = simulator.sensor.height, simulator.sensor.width
        expected = {
            "images": ((3, h, w, 3), np.uint8),
            "indentation": ((3, h, w), np.float32),
            "contact": ((3, h, w), np.bool_),
            "force": ((3,), np.float32),
            "penetration": ((3,), np.float32),
            "hit": ((3,), np.bool_),
            "advance": ((3,), np.float32),
            "contact_point": ((3, 3), None),
            "contact_c2w": ((3, 4, 4), None),
        }
        for field, (shape, dtype) in expected.items():
            value = getattr(pressed, field)
            assert isinstance(value, np.ndarray) and value.shape == shape, f"{field}: {getattr(value, 'shape', None)}"
            if dtype is not None:
                assert value.dtype == dtype, f"{field}: {value.dtype}, expected {np.dtype(dtype)}"

    def test_press_on_sphere_makes_contact_and_a_miss_does_not(self, simulator, pressed):
        force = self.forces(simulator.sensor)[0]
        assert pressed.hit.tolist() == [True, True, False]
        for i in (0, 1):
            assert pressed.contact[i].any() and pressed.indentation[i].max() > 0
            assert 0 < pressed.force[i] <= force * 1.05
            assert 0 < pressed.penetration[i] <= simulator.sensor.cfg.max_penetration * 1.001
            assert np.isfinite(pressed.advance[i]) and np.isfinite(pressed.contact_point[i]).all()
        assert not pressed.contact[2].any() and not np.isfinite(pressed.advance[2])
        assert np.isnan(pressed.contact_point[2]).all()

    def test_same_seed_same_images(self, simulator, pressed):
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=self.sphere_radius)
        again = simulator.press(sphere, self.poses(simulator.sensor), self.forces(simulator.sensor)[0], seed=0)
        assert np.array_equal(again.images, pressed.images)
        assert np.array_equal(again.contact, pressed.contact)

    def test_more_force_goes_deeper_over_a_larger_area(self, simulator, pressed):
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=self.sphere_radius)
        firm = simulator.press(sphere, self.poses(simulator.sensor)[:1], self.forces(simulator.sensor)[1], seed=0)
        assert firm.penetration[0] > pressed.penetration[0]
        assert firm.contact[0].sum() > pressed.contact[0].sum()
        assert firm.force[0] > pressed.force[0]

    def test_press_heights_to_a_penetration_and_to_a_force(self, simulator):
        s = simulator.sensor
        gaps = sphere_gaps(s, self.sphere_radius)[None]
        depth = 0.3 * s.cfg.max_penetration
        deep = simulator.press_heights(gaps, penetration=depth)
        assert deep.hit.tolist() == [True] and deep.contact[0].any()
        assert np.isclose(deep.indentation[0].max(), depth, rtol=0.05), (deep.indentation[0].max(), depth)
        assert deep.force[0] > 0
        force = self.forces(s)[0]
        pressed = simulator.press_heights(gaps, force=force)
        assert np.isclose(pressed.force[0], force, rtol=0.05), (pressed.force[0], force)
        with pytest.raises(TnfError):
            simulator.press_heights(gaps[:, :-1], force=force)  # not the sensor's pixel grid

    def test_press_heights_past_max_penetration_is_refused(self, simulator):
        s = simulator.sensor
        gaps = np.repeat(sphere_gaps(s, self.sphere_radius)[None], 2, 0)
        limit = s.cfg.max_penetration
        at_limit = simulator.press_heights(gaps[:1], penetration=limit)
        assert at_limit.penetration[0] == pytest.approx(limit, rel=1e-3)
        with pytest.raises(TnfError, match="max_penetration") as e:
            simulator.press_heights(gaps, penetration=[0.5 * limit, 1.5 * limit])
        assert "\n" not in str(e.value)


# -- object sources ---------------------------------------------------------------------------------
class ObjectSourceContract(_ComponentContract):
    """An object source (``tnf.objects.ObjectSource`` subclass) lists objects and loads them by name.

    Checks: registration and documented Config; config round trip; the source is named as registered and
    lists sorted, unique, non-empty names; each of the first ``max_objects`` objects is either a mesh (metres,
    centred at the origin, a plausible tabletop size, the same on a second load) or, for a source of camera
    images, an existing ``transforms.json``; an unknown name is an error naming it. Override the ``source``
    fixture for a source that needs files (build them with code).
    """

    registry = OBJECTS
    max_objects: ClassVar[int] = 2
    """How many of the source's objects the load test loads."""

    @pytest.fixture(scope="class")
    @classmethod
    def source(cls) -> Any:
        """The object source under test (built once per test class)."""
        return OBJECTS.build(cls.spec())

    def test_is_an_object_source_named_as_registered(self, source):

        assert isinstance(source, ObjectSource)
        assert source.name == self.name, "set the class attribute `name` to the registry name"
        names = source.names()
        assert names and names == sorted(set(names)) and all(isinstance(n, str) and n for n in names)

    def test_objects_load_as_the_contract_says(self, source):

        for name in source.names()[: self.max_objects]:
            views = source.views(name)
            if views is not None:
                assert views.is_file(), f"{name}: views() gives {views}, which is not a file"
                continue
            mesh = source.load(name)
            v = np.asarray(mesh.vertices)
            assert len(mesh.faces) > 0 and np.isfinite(v).all(), name
            assert np.allclose((v.max(0) + v.min(0)) / 2, 0, atol=1e-6), f"{name} is not centred"
            assert REFUSE_SIZE[0] <= float((v.max(0) - v.min(0)).max()) <= REFUSE_SIZE[1], name
            assert np.array_equal(np.asarray(source.load(name).vertices), v), f"{name} loads differently twice"

    def test_unknown_name_is_an_error_naming_it(self, source):
        with pytest.raises(TnfError, match="no_such_object"):
            source.load("no_such_object")
