"""The fusion network: corrects the motion method's frame at one instant from what TRMD, EDI,
the blurry frame and the events say there (:mod:`trmd_cli.fusion` makes its inputs).

A small U-Net (three scales, 16/32/64 channels, ≈ 0.12 M parameters) over seven planes per
instant k: the motion method's frame M(k), TRMD's frame, EDI's frame, B, the guard's weight
(the deconvolution's share in M(k)), the events' log-intensity change from the middle to k
(``c·V(k)``, clipped to ±3) and the instant ``(k − N)/N``. It returns ``M(k) + r``: the last
convolution starts at zero, so untrained it is the motion method itself. Colour frames are run
channel by channel (the weight, the events and the instant are shared).

Weights are a safetensors file (``fusion_default.safetensors`` ships in the package) whose
metadata says what it is (``format = "trmd-fusion"``) and what it was trained on.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..errors import WeightsError

__all__ = ["FusionNet", "FUSION_FORMAT", "DEFAULT_FUSION", "MAX_CONTRAST", "MAX_FALLBACK_CONTRAST",
           "default_fusion_path", "fusion_planes", "save_fusion", "load_fusion", "is_fusion_file",
           "describe_fusion"]

FUSION_FORMAT = "trmd-fusion"
#: the shipped fusion weights' file name, beside the RE-Net weights
DEFAULT_FUSION = "fusion_default.safetensors"
#: input planes per instant (see the module docstring)
PLANES = 7
#: the events' log-intensity change is clipped to this (hot pixels and bursts)
EVENT_CLIP = 3.0
#: the largest c at which the network corrects the motion method's frames wherever they are
#: used: the 99th percentile of the c settled on its training set's moving cameras (sensors
#: of c = 0.1–0.5; the estimate runs high). Beyond it the network fell 1.1 dB below the
#: motion method on a c = 0.7 set of large motions the motion method deblurs whole, and the
#: fused method keeps the motion method's frames where its guard trusts them
#: (:func:`~trmd_cli.fusion.motion_where_trusted`)
MAX_CONTRAST = 0.65
#: the largest c the network is used at where its motion input is EDI's frames with a
#: weight of 0 (binned data; where the motion method fell back): what it saw on the still
#: camera's samples of its training set, whose sensors reach c = 0.8 and whose settled c
#: spans the threshold search's whole range (to its bound, 1.0). On c = 0.75 binned frames
#: with ground truth, c settled per frame at 0.95 in the median, its frames were above TRMD's
#: (PSNR middle / sequence 29.90 / 28.15 against 29.80 / 27.23 dB;
#: ``bench/bench_still_camera.py``). Beyond it: TRMD's frames on bins, the motion method's
#: with event times
MAX_FALLBACK_CONTRAST = 1.0


def default_fusion_path() -> Path:
    """Where the shipped fusion weights are (the file may not exist)."""
    return Path(str(resources.files("trmd_cli") / "weights" / DEFAULT_FUSION))


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True))


class FusionNet(nn.Module):
    """(B, 7, H, W) planes → (B, 1, H, W) corrected frame (H, W any size: padded to ×4
    inside). ``width``: channels at full resolution (×2, ×4 at the coarser scales)."""

    def __init__(self, width: int = 16) -> None:
        super().__init__()
        w = int(width)
        self.width = w
        self.enc0 = _block(PLANES, w)
        self.enc1 = _block(w, 2 * w)
        self.enc2 = _block(2 * w, 4 * w)
        self.dec1 = _block(6 * w, 2 * w)
        self.dec0 = _block(3 * w, w)
        self.out = nn.Conv2d(w, 1, 3, padding=1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, planes: torch.Tensor) -> torch.Tensor:
        h, w = planes.shape[-2:]
        ph, pw = (-h) % 4, (-w) % 4
        x = F.pad(planes, (0, pw, 0, ph), mode="replicate") if ph or pw else planes
        e0 = self.enc0(x)
        e1 = self.enc1(F.avg_pool2d(e0, 2))
        e2 = self.enc2(F.avg_pool2d(e1, 2))
        d1 = self.dec1(torch.cat((F.interpolate(e2, scale_factor=2.0, mode="bilinear",
                                                align_corners=False), e1), 1))
        d0 = self.dec0(torch.cat((F.interpolate(d1, scale_factor=2.0, mode="bilinear",
                                                align_corners=False), e0), 1))
        out = x[:, :1] + self.out(d0)
        return out[..., :h, :w]


def fusion_planes(motion: np.ndarray, trmd: np.ndarray, edi: np.ndarray, blurry: np.ndarray,
                  weight: np.ndarray, events: np.ndarray, n: int) -> torch.Tensor:
    """The network's input for the 2N+1 instants of one exposure: (K·C, 7, H, W) float32.

    Args:
        motion, trmd, edi: (K, H, W[, 3]) frames [0, 1]; blurry: (H, W[, 3]).
        weight: (K, H, W) [0, 1]; events: (K, H, W) log-intensity change from the middle.
        n: N (the instant plane is ``(k − N)/N``).
    """
    k = motion.shape[0]
    colour = motion.ndim == 4
    h, w = motion.shape[1:3]

    def chans(a: np.ndarray) -> np.ndarray:  # (K, H, W[, C]) → (K, C, H, W)
        return a.transpose(0, 3, 1, 2) if colour else a[:, None]

    c = motion.shape[3] if colour else 1
    b = np.broadcast_to(chans(blurry[None]), (k, c, h, w))
    shared = (weight, np.clip(events, -EVENT_CLIP, EVENT_CLIP),
              np.broadcast_to(((np.arange(k) - n) / n)[:, None, None], (k, h, w)))
    planes = [chans(motion), chans(trmd), chans(edi), b] + \
        [np.broadcast_to(s[:, None], (k, c, h, w)) for s in shared]
    out = np.stack([np.asarray(p, np.float32) for p in planes], axis=2)  # (K, C, 7, H, W)
    return torch.from_numpy(np.ascontiguousarray(out.reshape(k * c, PLANES, h, w)))


def save_fusion(path: str | Path, model: FusionNet, meta: dict[str, Any],
                dtype: torch.dtype = torch.float32) -> Path:
    """Write ``model`` as safetensors (tensors in ``dtype``; read back as float32) with
    ``meta`` (JSON values) beside ``format``, ``width``; atomically."""
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {k: v.detach().to(dtype).contiguous() for k, v in model.state_dict().items()}
    info = {"format": FUSION_FORMAT, "width": str(model.width)}
    info.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()})
    tmp = path.with_name(path.name + ".part")
    save_file(tensors, str(tmp), metadata=info)
    tmp.replace(path)
    return path


def load_fusion(path: str | Path | None = None) -> tuple[FusionNet, dict[str, str]]:
    """The fusion network and its metadata from a safetensors file (default: the shipped
    one). Raises :class:`~trmd_cli.errors.WeightsError` with what is wrong, never a traceback
    of the loader."""
    from safetensors import SafetensorError, safe_open

    p = default_fusion_path() if path is None else Path(path)
    if not p.is_file():
        raise WeightsError("no fusion weights", path=p,
                           hint="build them with weights_recipe/train_fusion.py, or use "
                                "`--method motion` or `--method trmd`")
    try:
        with safe_open(str(p), framework="pt") as f:
            meta = dict(f.metadata() or {})
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError) as e:
        raise WeightsError(f"not a readable safetensors file ({e})", path=p) from None
    if meta.get("format") != FUSION_FORMAT:
        raise WeightsError(f"not fusion weights (format {meta.get('format')!r})", path=p,
                           hint="give a file written by weights_recipe/train_fusion.py")
    try:
        model = FusionNet(int(meta.get("width", "16")))
        model.load_state_dict({k: v.float() for k, v in tensors.items()})
    except (RuntimeError, ValueError) as e:
        raise WeightsError(f"fusion weights do not fit the network ({e})", path=p) from None
    return model.eval(), meta


def is_fusion_file(path: str | Path) -> bool:
    """Whether ``path`` is a safetensors file of fusion weights (by its metadata)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return (f.metadata() or {}).get("format") == FUSION_FORMAT
    except (SafetensorError, OSError, ValueError):
        return False


def describe_fusion(path: str | Path) -> dict[str, Any]:
    """What ``trmd info`` says of fusion weights: the network, its file, what it was trained
    on and its held-out figures (JSON values)."""
    from .weights import weights_hash

    model, meta = load_fusion(path)
    p = Path(path)

    def value(key: str) -> Any:
        v = meta.get(key)
        try:
            return json.loads(v) if v is not None else None
        except ValueError:
            return v

    return {"weights": "fusion network (--method fused)", "width": model.width,
            "parameters": sum(t.numel() for t in model.parameters()),
            "size_kib": round(p.stat().st_size / 1024, 1),
            "sha256": weights_hash(p),
            "trained_on": value("trained_on"), "steps": value("steps"),
            "held_out_psnr": value("held_out_psnr")}
