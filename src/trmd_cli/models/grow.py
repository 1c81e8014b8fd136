"""Growing a trained RE-Net: weights of a smaller network of the same family, loaded into a
larger one so that it computes exactly what the weights computed.

Three ways a network may have grown since its weights were trained, alone or together:

- a full-resolution refinement (``refine``) the weights lack: it starts as an identity on the
  last up-step's output (:meth:`~.blocks.Refinement.init_identity`);
- the sub-bin timing inputs (``timing``): the first convolutions of both feature extractors and
  the head gain input channels, appended after the old ones, whose weights start at zero;
- a wider U-Net (``widths``, ``refine_width``): the old weights sit at the old channels, weights
  from new input channels into old output channels are zero, and the new output channels keep
  their random initialisation, so they carry signal that those zero weights learn from.

The state-dict keys are those of the weights written so far; no key is renamed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from .blocks import Refinement
from .inputs import TimingInputs
from .renet import _DOWNS, RENet

__all__ = ["GROWN_PREFIXES", "TIMING_INPUTS", "Grown", "load_grown"]

#: parameter prefixes a network may lack in older weights: they start as an identity
GROWN_PREFIXES = ("refine.",)
#: weights whose input channels grow with ``timing`` (the new ones are appended, zero)
TIMING_INPUTS = ("blur_fe.conv1.0.weight", "event_fe.conv1.0.weight", "head.weight")


@dataclass(frozen=True)
class Grown:
    """What :func:`load_grown` grew; empty when the weights fitted as they were.

    Attributes:
        identity: tensors the weights lacked, started as an identity (the refinement).
        timing: tensors that gained the timing input channels, at zero.
        widened: tensors of the U-Net grown wider.
    """

    identity: tuple[str, ...] = ()
    timing: tuple[str, ...] = ()
    widened: tuple[str, ...] = ()

    @property
    def names(self) -> list[str]:
        """Every tensor that was grown (a name may appear under two headings)."""
        return [*self.identity, *self.timing, *self.widened]


def load_grown(net: RENet, state: Mapping[str, torch.Tensor]) -> Grown:
    """Load ``state`` into ``net``: weights of the same network, or of one without the
    refinement, without the timing inputs and/or with a narrower U-Net.

    Every tensor of ``state`` must fit, except as the module docstring says; either way ``net``
    then computes exactly what the weights computed before.

    Raises:
        RuntimeError: unexpected, mismatched or other missing tensors (as
            ``load_state_dict``); a U-Net wider than ``net``'s.
    """
    state, widened = _widen_state(net, dict(state))
    own = net.state_dict()
    timed: list[str] = []
    enc = net.encoder
    if isinstance(enc, TimingInputs):
        blur_add = enc.blur_channels - enc.prior.blur_channels
        event_add = enc.event_channels - enc.prior.event_channels
        extra = dict(zip(TIMING_INPUTS, (blur_add, event_add, blur_add + event_add)))
        for name, add in extra.items():
            old, new = state.get(name), own[name]
            if (old is not None and old.shape[1] + add == new.shape[1]
                    and old.shape[0] == new.shape[0] and old.shape[2:] == new.shape[2:]):
                grown = torch.zeros_like(new)
                grown[:, :old.shape[1]] = old.to(new.dtype)
                state[name] = grown
                timed.append(name)
        if timed and len(timed) != len(extra):
            raise RuntimeError(f"Error(s) in loading state_dict: only {timed} lack the "
                               "timing inputs")
    missing, unexpected = net.load_state_dict(state, strict=False)
    other = [k for k in missing if not k.startswith(GROWN_PREFIXES)]
    grown_refine = {k for k in own if k.startswith(GROWN_PREFIXES)}
    if missing and not other and set(missing) != grown_refine:
        other = sorted(set(missing))  # part of a refinement: not a network to grow from
    if other or unexpected:
        raise RuntimeError(f"Error(s) in loading state_dict: missing {other[:3]}, "
                           f"unexpected {list(unexpected)[:3]}")
    if missing:
        assert isinstance(net.refine, Refinement)
        net.refine.init_identity()
    return Grown(identity=tuple(missing), timing=tuple(timed), widened=tuple(widened))


def _unet_layouts(net: RENet, old: dict[str, int]) -> dict[str, tuple[list, list]]:
    """Per U-Net module: (output, input) channel layouts as [(old, new) …] segments —
    concatenated inputs have one segment per part — for widths ``old`` → ``net``'s."""
    own = dict(zip(("w0", "w1", "w2", "w3"), net.args["widths"]),
               hs=net.up_width, rw=net.args.get("refine_width", net.up_width))
    seg = {k: (old[k], own[k]) for k in own}
    fw = net.args["feat_width"]
    feat = (fw, fw)
    out: dict[str, tuple[list, list]] = {
        "down1.0": ([seg["w0"]], [feat]), "down2.0": ([seg["w1"]], [seg["w0"]]),
        "down3.0": ([seg["w2"]], [seg["w1"]]), "down4.0": ([seg["w3"]], [seg["w2"]]),
        "up1.0": ([seg["w2"]], [seg["w3"]]),
        "up2.0": ([seg["w1"]], [seg["w2"], seg["w2"]]),
        "up3.0": ([seg["w0"]], [seg["w1"], seg["w1"]]),
        "up4.0": ([seg["hs"]], [seg["w0"], seg["w0"]]),
    }
    for i in range(len(net.res)):
        for j in (0, 1, 3, 4):
            out[f"res.{i}.body.{j}"] = ([seg["w3"]], [seg["w3"]])
    if isinstance(net.refine, Refinement):
        k = len(net.refine)
        for i in range(k):
            ins = [seg["hs"], feat] if i == 0 else [seg["rw"]]
            out[f"refine.{i}.0"] = ([seg["hs"] if i == k - 1 else seg["rw"]], ins)
    rest = net.head.weight.shape[1] - net.up_width
    out["head"] = ([(net.head.weight.shape[0],) * 2], [seg["hs"], (rest, rest)])
    return out


def _widen_state(net: RENet, state: dict[str, torch.Tensor]
                 ) -> tuple[dict[str, torch.Tensor], list[str]]:
    """``state`` of a narrower U-Net (same feature extractors and fusion) placed in ``net``'s
    tensors. Returns the state and the names widened ([] when none)."""
    own = net.state_dict()
    if "down1.0.weight" not in state or \
            state["down1.0.weight"].shape[0] == own["down1.0.weight"].shape[0]:
        return state, []
    old = {f"w{i}": state[f"down{i + 1}.0.weight"].shape[0] for i in range(_DOWNS)}
    old["hs"] = state["up4.0.weight"].shape[1]
    old["rw"] = state["refine.0.0.weight"].shape[0] if "refine.0.0.weight" in state \
        else old["hs"]

    layouts = _unet_layouts(net, old)
    if any(o > n for outs, ins in layouts.values() for o, n in outs + ins):
        raise RuntimeError("Error(s) in loading state_dict: the weights' U-Net is wider "
                           "than this network's (a network can grow, not shrink)")

    def old_index(layout: list) -> torch.Tensor:
        idx, off = [], 0
        for o, n in layout:
            idx.append(torch.arange(off, off + o))
            off += n
        return torch.cat(idx)

    state, widened = dict(state), []
    for module, (outs, ins) in layouts.items():
        oi, ii = old_index(outs), old_index(ins)
        for name in [k for k in own if k.rsplit(".", 1)[0] == module]:
            if name not in state or state[name].shape == own[name].shape:
                continue  # unchanged, or a scalar (BatchNorm's step count)
            src, dst = state[name], own[name].clone()
            if dst.ndim == 1:
                dst[oi] = src.to(dst.dtype)
            else:
                # ConvTranspose2d stores (in, out, k, k), Conv2d (out, in, k, k)
                o_dim, i_dim = (1, 0) if module.startswith("up") else (0, 1)
                new_in = torch.ones(dst.shape[i_dim], dtype=torch.bool)
                new_in[ii] = False
                rows = dst.index_select(o_dim, oi)
                rows.index_fill_(i_dim, new_in.nonzero().flatten(), 0.0)
                if src.shape[i_dim] != len(ii) or src.shape[o_dim] != len(oi):
                    raise RuntimeError(f"Error(s) in loading state_dict: size mismatch for "
                                       f"{name}: {tuple(src.shape)} does not fit "
                                       f"{tuple(dst.shape)} grown")
                rows.index_copy_(i_dim, ii, src.to(dst.dtype))
                dst.index_copy_(o_dim, oi, rows)
            state[name] = dst
            widened.append(name)
    return state, widened
