"""The ``simulated`` VL encoder's settings: ground-truth label mixtures in MiniLM text space.
Torch-free: ``build`` imports the encoder."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.perception.encoders.config import VL_ENCODERS, VLEncoderBackend


@VL_ENCODERS.register("simulated")
class SimulatedVLConfig(VLEncoderBackend):
    """Ground-truth label mixtures in MiniLM text space: measures the mapping, not CLIP."""

    backend: Literal["simulated"] = "simulated"
    """Ground-truth labels embedded by a real offline text encoder; synthetic scenes only
    (shared/perception/encoders/simulated.py)."""
    noise_std: float = Field(0.05, ge=0)
    """Gaussian noise added before normalisation."""
    ground_truth: str | None = None
    """The synthetic sequence folder (``SEQ_DIR``; its ``gt/`` subfolder is accepted too). The
    encoder mixes the labels of ``gt/gt_categories.json`` by the instance images of
    ``instances/``, read by keyframe index for crops and by pixel content for image queries.
    ``trackgraph map``, ``launch`` and ``serve --sequence`` set it to the sequence when
    unset."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from shared.perception.encoders.simulated import SimulatedVLEncoder

        # The text encoder stays on the CPU: its embeddings are cached on disk by text, and
        # a crop costs no network pass at all.
        return SimulatedVLEncoder(self.ground_truth, noise_std=self.noise_std, source=ground_truth)
