"""Settings of the generator stages, as validated dataclasses: ``TrainSettings`` (the ``train`` section, read by
``tnf.stages.train``), ``FinetuneSettings`` (the ``finetune`` section, read by ``tnf.stages.finetune``) and
``GenerateSettings`` (the ``generate`` section, read by ``tnf.generators.generate``).

Kept apart from the modules that use them, which import torch, so that every stage checks every section
before any work without importing it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tnf.objects import TOUCH_SPLITS
from tnf.registry import FROM_YAML, SettingError, at_least, yaml_defaults, yaml_field

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""torch.compile's modes, which ``train.compile`` also takes by name."""


@dataclass
@yaml_defaults("train/default")
class TrainSettings:
    """The ``train`` section: how long a generator trains, and how its run is checkpointed and logged."""

    run_name: str | None = yaml_field(identity=False)
    """Run folder name under ``<data_root>/models/``; null: the run id (``tnf.generators.names.run_id``)."""
    epochs: int = FROM_YAML
    """Training epochs in all."""
    decay_epochs: int = FROM_YAML
    """The last this many of the epochs decay the learning rate linearly to zero."""
    ema_decay: float | None = FROM_YAML
    """Decay per step of an exponential moving average of the generator's weights, which validates and
    generates; null: none."""
    patience: int | None = yaml_field(identity=lambda s: s.patience is not None)
    """Stop at a plateau: after this many validations in a row whose SSIM did not rise above the best by more than
    ``min_delta`` (``epochs`` stays the most it trains); null: train all ``epochs``."""
    min_delta: float = yaml_field(identity=lambda s: s.patience is not None)
    """The least rise of validation SSIM that counts as an improvement for ``patience``."""
    resume: bool = yaml_field(identity=False)
    """Continue an unfinished run from its ``last.ckpt`` (false: start it again)."""
    force: bool = yaml_field(identity=False)
    """Train again even when the run finished with the same settings."""
    limit_train_batches: int | float | None = FROM_YAML
    """Training batches per epoch: null all, an integer that many, a float in (0, 1] that fraction."""
    limit_val_batches: int | float | None = FROM_YAML
    """Validation batches per epoch (as ``limit_train_batches``)."""
    checkpoint_every_s: float = yaml_field(identity=False)
    """Least seconds between writes of ``last.ckpt`` at the end of an epoch (0: every epoch; always after the
    last)."""
    log_every_n_steps: int = FROM_YAML
    """Steps between rows of logged training losses."""
    grid_rows: int = FROM_YAML
    """Validation pairs in each epoch's image grid."""
    finite_check_every: int = FROM_YAML
    """Steps between checks of the losses for NaN/Inf (also before each checkpoint)."""
    compile: bool | Literal["default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"] = yaml_field(
        identity=False
    )
    """Run the generator's networks through torch.compile: true (its default mode), false, or a mode of
    ``COMPILE_MODES``; the same losses to float tolerance, faster on a GPU."""

    def validate(self) -> None:
        at_least(self, 0, "epochs", "decay_epochs", "checkpoint_every_s", "log_every_n_steps")
        at_least(self, 0, "grid_rows", "finite_check_every", "min_delta")
        at_least(self, 1, "patience")


@dataclass
@yaml_defaults("finetune/default")
class FinetuneSettings:
    """The ``finetune`` section: continuing a trained generator (or training one from scratch) on a small
    dataset of another sensor, or on real indenter presses."""

    checkpoint: str | None = yaml_field(identity=False)
    """Checkpoint to start from: a path, ``<run>/<file>`` under ``<data_root>/models/``, a run (its best.ckpt)
    or a run family (``tnf.generators.names.run_family``); null: from scratch. A run's key records the file
    it resolves to and its hash instead."""
    run_name: str | None = yaml_field(identity=False)
    """Run folder name under ``<data_root>/models/``; null: the run id (``tnf.generators.names.run_id``)."""
    epochs: int = FROM_YAML
    """Fine-tuning epochs in all."""
    decay_epochs: int = FROM_YAML
    """The last this many of the epochs decay the learning rate linearly to zero."""
    lr: float | None = FROM_YAML
    """Learning rate for fine-tuning; null: the generator's own."""
    freeze: list[str] = FROM_YAML
    """Parameter-name prefixes kept fixed; []: everything trains."""
    ema_decay: float | None = FROM_YAML
    """Decay per step of an exponential moving average of the generator's weights (as ``train.ema_decay``);
    null: none."""
    resume: bool = yaml_field(identity=False)
    """Continue an unfinished fine-tuning run from its ``last.ckpt``."""
    force: bool = yaml_field(identity=False)
    """Train again even when the run finished with the same settings."""
    limit_train_batches: int | float | None = FROM_YAML
    """Training batches per epoch: null all, an integer that many, a float in (0, 1] that fraction."""
    limit_val_batches: int | float | None = FROM_YAML
    """Validation batches per epoch (as ``limit_train_batches``)."""
    checkpoint_every_s: float = yaml_field(identity=False)
    """Least seconds between writes of ``last.ckpt`` at the end of an epoch (0: every epoch; always after the
    last)."""
    log_every_n_steps: int = FROM_YAML
    """Steps between rows of logged training losses."""
    grid_rows: int = FROM_YAML
    """Validation pairs in each epoch's image grid."""
    finite_check_every: int = FROM_YAML
    """Steps between checks of the losses for NaN/Inf."""
    val_every_n_epochs: int = FROM_YAML
    """Validation (``best.ckpt``, the image grid) after every this many epochs."""
    presses: str | None = FROM_YAML
    """Real indenter presses to fine-tune on instead of ``data.datasets``: a press folder or ``taxim:SENSOR``;
    null: the paired datasets."""
    press_train: list[int] = FROM_YAML
    """Presses whose real frames the generator trains on (default: ``calibrate.train``)."""
    press_val: list[int] = FROM_YAML
    """Validation presses; []: the training presses serve as validation pairs too."""
    press_test: list[int] = FROM_YAML
    """Held-out presses scored against their real frames after training (default: ``calibrate.test``)."""
    press_depth_scale: float = FROM_YAML
    """Factor on each press's depth (the calibration's depth factor)."""
    press_reference: str = FROM_YAML
    """Where depth 0.5 lies in a press's RGB-D: ``gel`` (the pressed gel's plane) or ``contact`` (the first
    contact), checked by the stage (``tnf.real.generated.REFERENCES``)."""
    press_sim_pairs: int = FROM_YAML
    """Training pairs of the simulated dataset that join the press pairs (T-N+)."""

    def validate(self) -> None:
        at_least(self, 0, "epochs", "decay_epochs", "checkpoint_every_s", "log_every_n_steps")
        at_least(self, 0, "grid_rows", "finite_check_every", "press_sim_pairs")
        at_least(self, 1, "val_every_n_epochs")
        if not self.press_depth_scale > 0:
            raise SettingError("press_depth_scale", f"must be > 0, got {self.press_depth_scale}")


def _in_cone(settings: GenerateSettings) -> bool:
    return settings.directions == "novel_view"


@dataclass
@yaml_defaults("generate/default")
class GenerateSettings:
    """The ``generate`` section: which model, which poses, where the images go."""

    model: str | None = FROM_YAML
    """Trained generator: a run folder under ``<data_root>/models/``; null: the stage names the model ``tnf
    train`` trains with the same config."""
    checkpoint: str = FROM_YAML
    """Checkpoint file inside the model folder."""
    run_name: str | None = yaml_field(identity=False)
    """Output folder name under ``<data_root>/generated/``; null: the model's run name."""
    n_poses: int = FROM_YAML
    """Poses sampled per object on a sphere around it (ignored with ``poses_file``)."""
    directions: Literal["sphere", "novel_view"] = FROM_YAML
    """Where sampled poses look from: ``sphere`` (every direction) or ``novel_view`` (inside the touch stage's
    held-out cone)."""
    cone_axis: tuple[float, float, float] = yaml_field(identity=_in_cone)
    """Centre direction of the held-out cone for ``directions=novel_view`` (default: ``touch.novel_view_axis``)."""
    cone_deg: float = yaml_field(identity=_in_cone)
    """Half-angle of that cone, degrees (default: ``touch.novel_view_cone``)."""
    poses_file: str | None = FROM_YAML
    """Camera-to-world poses to use instead of sampling: ``.npy`` ``[N, 4, 4]`` or ``.json``, metres."""
    radius: float = FROM_YAML
    """Distance of the sampled poses from the object centre, metres (default: ``touch.radius``)."""
    up: tuple[float, float, float] = FROM_YAML
    """World up vector that fixes the roll of sampled poses (default: ``touch.up``)."""
    random_roll: bool = FROM_YAML
    """Rotate each sampled pose randomly about its view axis (default: ``touch.random_roll``)."""
    dataset: str | None = FROM_YAML
    """Paired dataset whose preprocessing (crop, depth normalisation) is copied; null: the model's first
    training dataset."""
    crop_px: int | None = FROM_YAML
    """A fixed square crop in capture-camera pixels in place of the dataset's framing; null: the dataset's."""
    split: str = FROM_YAML
    """Split label written for each generated touch (``train``, ``val`` or ``novel_view``)."""
    batch_size: int = yaml_field(identity=False)
    """Poses rendered and generated per batch."""
    render_chunk: int | None = yaml_field(identity=False)
    """Rays per chunk inside the scene renderer; null: the scene's default."""
    mirror_average: bool = FROM_YAML
    """Average each image with the generator's image of the mirrored touch, mirrored back, where the sensor has a
    left-right mirror symmetry."""
    touch_force: float | list[float] | str | None = FROM_YAML
    """Force of each generated touch, newtons, for a model trained with force: a number, a list, ``"low:high:count"``
    or ``sim`` (the object's simulated touches' poses and forces); null: ``touch.force`` for such a model."""
    force: bool = yaml_field(
        identity=False,
        hint=" (it redoes finished images; the force of a generated touch is generate.touch_force)",
    )
    """Generate again even when the output exists with the same settings."""

    def validate(self) -> None:
        at_least(self, 0, "n_poses")
        at_least(self, 1, "batch_size", "crop_px", "render_chunk")
        if self.split not in TOUCH_SPLITS:
            raise SettingError("split", f"must be one of {', '.join(TOUCH_SPLITS)}, got {self.split!r}")
