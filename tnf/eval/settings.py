"""Settings of ``tnf evaluate``, as validated dataclasses: ``EvaluateSettings`` (the ``evaluate`` section, read
by ``tnf.eval.run`` and ``tnf.eval.force``) with its nested sections ``ByForceSettings``, ``ClassifySettings``
and ``ClassifierConfig`` (read by ``tnf.eval.classify``).

Kept apart from the modules that use them, which import torch, so that every stage checks every section before
any work without importing it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from tnf.errors import TnfError
from tnf.registry import FROM_YAML, at_least, yaml_defaults, yaml_field


@dataclass
@yaml_defaults("evaluate/default", node="by_force")
class ByForceSettings:
    """Evaluation by force of a model conditioned on the force (docs/force.md)."""

    sweep: list[float] | None = FROM_YAML
    """Forces, newtons, ascending, that each test pose is generated at for the growth check and the figure;
    null: 6 forces from the dataset's force range to the top of its extrapolation band."""
    area_threshold: float = FROM_YAML
    """A pixel is in contact where ``|image - background|`` (0-255 scale, mean over RGB) exceeds this."""
    figure_split: str = FROM_YAML
    """Split whose first touch with a contact the figure shows (the first scored split if it is not scored)."""
    simulator_poses: int = FROM_YAML
    """Touches of the figure split pressed again by the simulator at the sweep's forces (the reference for the
    generator's share of poses whose contact area grows with force); 0 skips it."""

    def validate(self) -> None:
        at_least(self, 0, "simulator_poses")


@dataclass
@yaml_defaults("evaluate/default", node="classify")
class ClassifySettings:
    """The classification task: rows Sim, Sim + G and G only."""

    enabled: bool = FROM_YAML
    """Run the classification task."""
    sensor: str | None = FROM_YAML
    """Sensor whose ground-truth touches (``<data_root>/touch/<sensor>/<source>/<object>/``) are used; null: the
    run's sensor."""
    objects: list[str] | None = FROM_YAML
    """Objects to classify (the classes); null: every object with touches, filtered by ``object_names``."""
    sim_per_object: int = FROM_YAML
    """Ground-truth touches per object in the Sim set (at least 1: a row needs images)."""
    sim_splits: list[str] = FROM_YAML
    """Touch splits the Sim set draws from."""
    generated_per_object: int | None = FROM_YAML
    """Generated touches per object added in Sim + G and used alone in G only; null: all."""
    test_splits: list[str] = FROM_YAML
    """Held-out ground-truth touch splits that make the test set (the same for every row)."""
    test_per_object: int | None = FROM_YAML
    """Test touches per object; null: all."""
    generated_only: bool = FROM_YAML
    """Also train on generated images alone (the G only row)."""

    def validate(self) -> None:
        at_least(self, 1, "sim_per_object")
        at_least(self, 0, "generated_per_object", "test_per_object")


@dataclass
@yaml_defaults("evaluate/default", node="classifier")
class ClassifierConfig:
    """Settings of the tactile object classifier (identical for every training set)."""

    image_size: int = FROM_YAML
    """Side of the square input image in pixels (128 is the generators' size; 64 trains 4x faster)."""
    width: int = FROM_YAML
    """Channels of the first convolution block; doubled in each of the next blocks (up to 4 blocks)."""
    steps: int = FROM_YAML
    """Optimisation steps (batches); the same for every row, so a larger training set gets no extra steps."""
    batch_size: int = FROM_YAML
    """Images per step."""
    lr: float = FROM_YAML
    """Adam learning rate, decayed with a cosine schedule to zero over ``steps``."""
    weight_decay: float = FROM_YAML
    """AdamW weight decay."""
    shift: int = FROM_YAML
    """Augmentation: random translation of each batch by up to this many pixels (0 = none)."""
    real_fraction: float | None = FROM_YAML
    """In a training set that mixes ground-truth and generated images (``Sim + G``), the share of each batch drawn
    from the ground truth; None draws batches uniformly from the whole set, so adding generated images also cuts
    how often each ground-truth image is seen. Sets of one kind (``Sim``, ``G only``) are drawn as with None."""
    restarts: int = FROM_YAML
    """Classifiers trained per row, each from its own seed and (in ``tnf evaluate``) its own draw of the Sim
    touches; the row's accuracy is their mean. With a small test set or a few Sim touches per object, one
    classifier's spread can exceed the difference between rows; more restarts average it out."""

    def validate(self) -> None:
        if self.image_size < 16:
            raise TnfError(f"evaluate.classifier.image_size must be >= 16 pixels, got {self.image_size}")
        for name in ("width", "steps", "batch_size", "restarts"):
            if getattr(self, name) < 1:
                raise TnfError(f"evaluate.classifier.{name} must be >= 1, got {getattr(self, name)}")
        if self.lr <= 0:
            raise TnfError(f"evaluate.classifier.lr must be > 0, got {self.lr}")
        if not 0 <= self.shift < self.image_size // 2:
            raise TnfError(f"evaluate.classifier.shift must be in [0, image_size/2), got {self.shift}")
        if self.real_fraction is not None and not (
            isinstance(self.real_fraction, (int, float))
            and not isinstance(self.real_fraction, bool)
            and 0 < self.real_fraction < 1
        ):
            raise TnfError(
                f"evaluate.classifier.real_fraction must be null or a number in (0, 1), got {self.real_fraction!r}"
            )

    @classmethod
    def from_dict(cls, params: Mapping[str, Any]) -> ClassifierConfig:
        """Build and validate from a config node; an unknown key is a TnfError naming it."""
        known = {f.name for f in dataclasses.fields(cls)}
        for key in params:
            if key not in known:
                raise TnfError(f"unknown key evaluate.classifier.{key}; known: {', '.join(sorted(known))}")
        cfg = cls(**dict(params))
        cfg.validate()
        return cfg


@dataclass
@yaml_defaults("evaluate/default")
class EvaluateSettings:
    """The ``evaluate`` section: which model, which test sets, the classification task and the report."""

    name: str = yaml_field(identity=False)
    """Report name: the report goes to ``<data_root>/reports/<name>/``."""
    notes: str | None = yaml_field(identity=False)
    """Markdown that ends the report."""
    next: str | None = yaml_field(identity=False)
    """Markdown that ends the report's opening verdict: what to run next."""
    model: str | None = FROM_YAML
    """Trained generator to evaluate: a run folder under ``<data_root>/models/``; null: only rebuild the report."""
    checkpoint: str = FROM_YAML
    """Checkpoint file inside the model folder."""
    dataset: str | None = FROM_YAML
    """Paired dataset with the test splits (a name under ``<data_root>/pairs/`` or a path); null: the first of
    ``data.datasets``."""
    generated: str | None = FROM_YAML
    """Generated touches of this model: a run folder under ``<data_root>/generated/``; null: ``model``."""
    method: str | None = FROM_YAML
    """Row label in the tables; null: from the generator (tn_cgan: T-N, lee: Lee, cyclegan: Cycle)."""
    table: Literal["main", "transfer"] = FROM_YAML
    """Which table the run belongs to: ``main`` (the paper's Table 1) or ``transfer`` (its Table 2)."""
    sweep_dir: str | None = yaml_field(identity=False)
    """A Hydra multirun folder whose results.json files join the report; null: none."""
    force: bool = yaml_field(identity=False)
    """Evaluate again even when this run's results exist with the same settings, and replace another model's in
    its row."""
    splits: list[str] = FROM_YAML
    """Test splits scored with SSIM and MSE against ground truth; ``[]`` skips the image metrics."""
    per_object: int | None = FROM_YAML
    """Test pairs per object and split; null: all."""
    batch_size: int = FROM_YAML
    """Pairs per batch when generating test images (the generator's noise is drawn per batch: part of a run's
    identity)."""
    num_workers: int = yaml_field(identity=False)
    """Data-loader worker processes."""
    examples: int = FROM_YAML
    """Novel-object touches shown in the example figure."""
    diff_threshold: float = FROM_YAML
    """Example figure: pixels whose ``|generated - target|`` (0-255 scale, mean over RGB) is below this are black."""
    by_force: ByForceSettings = FROM_YAML
    """Evaluation by force, for a model conditioned on the force."""
    classify: ClassifySettings = FROM_YAML
    """The classification task."""
    classifier: ClassifierConfig = FROM_YAML
    """The classifier, identical for every training set."""

    def validate(self) -> None:
        at_least(self, 0, "per_object", "num_workers", "examples")
        at_least(self, 1, "batch_size")
