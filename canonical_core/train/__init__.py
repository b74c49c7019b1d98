"""Training of the decoder's learned heads on posed RGB-D captures, and their checkpoints.

- checkpoints (`decode.checkpoint`, re-exported here): safetensors files (save, load with checks,
  apply to a decoder) and the `SceneConfig.model` setting's resolution;
- `data`: captures at reduced resolution, fused scenes of sampled input views (cached), and a
  differentiable decode of their sums;
- `losses`: the render loss (MSE plus SSIM) on held-out frames;
- `loop`: the training loop, its report (loss curves, held-out PSNR before and after) and the
  ``canonical train`` entry point.

Only the checkpoint functions are imported here; the loop (which imports the evaluation) is
imported as ``canonical_core.train.loop``.
"""

from ..decode.checkpoint import (CHECKPOINT_FORMAT, CHECKPOINT_VERSION, TRAINED_HEADS, Checkpoint, apply_checkpoint,
                         load_checkpoint, load_model, resolve_model, save_checkpoint)

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "TRAINED_HEADS", "Checkpoint", "apply_checkpoint",
           "load_checkpoint", "load_model", "resolve_model", "save_checkpoint"]
