"""TRMD and the motion method, fused: what a small trained network
(:class:`~trmd_cli.models.fusion.FusionNet`) reads and how the fused frames are made.

The motion method (:func:`~trmd_cli.deconv.motion_deblur`) recovers from B the texture no event
recorded, wherever its global motion explains the blur; RE-Net knows the events' edges and
copes with what moves on its own; EDI is the events' reading. Per latent instant k, the fusion
network is given the three frames, B, the motion guard's weight and the events between the
middle instant and k (as the log-intensity change ``c·V(k)``), and corrects the motion method's
frame. Its last layer starts at zero, so an untrained network returns the motion method exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .edi import check_blurry
from .events import EventStream, Exposure

__all__ = ["FusionInputs", "fusion_inputs", "fusion_inputs_from_bins", "keep_where_quiet",
           "motion_where_trusted", "QUIET_SIGMA", "QUIET_SHARE"]


@dataclass(frozen=True, eq=False)
class FusionInputs:
    """What the fusion network reads for one exposure, at its 2N+1 instants k/2N.

    Attributes:
        blurry: (H, W[, 3]) float32 [0, 1].
        edi, trmd, motion: (2N+1, H, W[, 3]) float32, the three methods' frames.
        weight: (2N+1, H, W) float32 [0, 1], the motion deconvolution's share in ``motion``
            (0 where the guard fell back to EDI).
        events: (2N+1, H, W) float32, ``c · V(k)``: the log-intensity change from the middle
            instant to k the events report (0 at k = N).
        fired: (H, W) bool, the pixels whose events say the scene changed there: those EDI's
            model holds for a stream (without the hot pixels' and the isolated ones, the
            sensor's noise); every pixel with a count for bins (the isolation test on bins,
            coarse in time, left out counts the scene fired: 0.1 dB lower at c = 0.75).
        prepared: the exposure as settled once for all three
            (:class:`~trmd_cli.methods.Prepared`: c, the hot pixels, the per-pixel sort).
        notes: what the user should know (the motion method's fallbacks).
    """

    blurry: np.ndarray
    edi: np.ndarray
    trmd: np.ndarray
    motion: np.ndarray
    weight: np.ndarray
    events: np.ndarray
    fired: np.ndarray
    prepared: object
    notes: tuple[str, ...] = ()

    @property
    def contrast(self) -> float:
        """c used throughout."""
        return float(self.prepared.contrast)


def fusion_inputs(blurry: np.ndarray, events: EventStream, exposure: Exposure, trmd,
                  n: int, prepared=None, noise: float | None = None) -> FusionInputs:
    """Run EDI, TRMD and the motion method on one exposure as ``trmd deblur`` runs each.

    Args:
        blurry: (H, W[, 3]) float32 [0, 1]; events, exposure: the stream and its window (µs).
        trmd: a :class:`~trmd_cli.methods.TrmdMethod` (its c, given, per recording or per
            frame, is the c of all three).
        n: 2N+1 instants; must be the weights' N.
        prepared: the exposure already settled by ``trmd.prepare`` (None: settled here).
        noise: the σ the deconvolution is weighed by when ``blurry`` had its fixed pattern
            removed (see :func:`~trmd_cli.methods.motion_frames`).
    """
    from .methods import motion_frames
    from .threads import beside
    from .voxel import scer_voxels

    b = check_blurry(blurry, events.width, events.height)
    prep = trmd.prepare(b, events, exposure) if prepared is None else prepared
    # TRMD's network (torch, outside the interpreter) runs beside the motion method, whose
    # contrast maximisation keeps one core busy and leaves the other mostly idle: 1.58 →
    # 1.33 s per 346×260 frame on 2 cores, the same frames (one thread per process: in turn)
    later = beside(trmd.grid_frames, b, events, exposure, prep, lane="network")
    fr = np.arange(2 * n + 1) / (2 * n)
    edi, res = motion_frames(b, events, exposure, fr, prep, noise=noise)
    frames = later.result()
    h, w = b.shape[:2]
    weight = np.zeros((2 * n + 1, h, w), np.float32) if res.weights is None else res.weights
    vox = scer_voxels(events, exposure, n, window=prep.window)
    dlog = np.zeros((2 * n + 1, h, w), np.float32)
    k = [i for i in range(2 * n + 1) if i != n]
    dlog[k] = prep.contrast * vox
    if prep.hot is not None:
        dlog[:, prep.hot] = 0.0
    return FusionInputs(b, edi.astype(np.float32), frames.astype(np.float32),
                        res.frames.astype(np.float32), weight.astype(np.float32), dlog,
                        prep.model.fired(), prep, res.notes)


def fusion_inputs_from_bins(blurry: np.ndarray, bins: np.ndarray, trmd, n: int,
                            prepared=None) -> FusionInputs:
    """What the network reads for one exposure given as binned counts, which hold no event
    times to find a motion in: the motion method's frames are its fallback, EDI's, with a
    weight of 0 (as the network saw them in training wherever the guard fell back).

    Args:
        blurry: (H, W[, 3]) float32 [0, 1], checked; bins: (M, H, W) signed counts of M equal
            bins spanning the exposure, checked.
        trmd: a :class:`~trmd_cli.methods.TrmdMethod` (its c is the c of both).
        n: 2N+1 instants; must be the weights' N.
        prepared: the exposure already settled by ``trmd.prepare`` (None: settled here).
    """
    from .methods import bin_grid, bins_for
    from .voxel import scer_from_bins

    prep = trmd.prepare(blurry, bins) if prepared is None else prepared
    edi = prep.model.latent(blurry, bin_grid(n), prep.contrast).astype(np.float32)
    frames = trmd.bin_frames(blurry, bins, prep).astype(np.float32)
    h, w = blurry.shape[:2]
    dlog = np.zeros((2 * n + 1, h, w), np.float32)
    dlog[[i for i in range(2 * n + 1) if i != n]] = prep.contrast * scer_from_bins(
        bins_for(bins, n))
    return FusionInputs(blurry, edi, frames, edi, np.zeros((2 * n + 1, h, w), np.float32),
                        dlog, np.any(bins != 0, axis=0), prep)


#: Gaussian σ (px) of the neighbourhood whose share of fired pixels says whether something moved
QUIET_SIGMA = 6.0
#: the share of fired pixels in that neighbourhood from which the network's frame is kept whole
QUIET_SHARE = 0.05


def keep_where_quiet(fused: np.ndarray, edi: np.ndarray, weight: np.ndarray,
                     fired: np.ndarray) -> np.ndarray:
    """The fused frames, with EDI's where nothing says that anything moved: the motion method
    fell back there (weight 0) and hardly an event fired around (under :data:`QUIET_SHARE` of
    the pixels within about :data:`QUIET_SIGMA` px, blended in between).

    Such a pixel saw a change of less than c over the exposure, so B is its latent frame at
    every instant as far as anything measured tells, and EDI's frame is B there. The network
    learnt from cameras that shook by up to a pixel without firing at a high threshold, and
    sharpened what a still scene holds sharp: on a tripod at c = 0.75 its middle frame was up
    to 6 dB below EDI's (``bench/bench_still_camera.py``).

    Args:
        fused, edi: (2N+1, H, W[, 3]) float32, the network's frames and EDI's.
        weight: (2N+1, H, W) float32 [0, 1], the motion deconvolution's share in its frames.
        fired: (H, W) bool, the pixels whose events say the scene changed there
            (:attr:`FusionInputs.fired`).
    Returns:
        (2N+1, H, W[, 3]) float32.
    """
    import cv2

    share = cv2.GaussianBlur(fired.astype(np.float32), (0, 0), QUIET_SIGMA)
    keep = np.maximum(np.minimum(share / QUIET_SHARE, 1.0)[None], weight > 0)
    if fused.ndim == 4:
        keep = keep[..., None]
    return (edi + keep * (fused - edi)).astype(np.float32)


def motion_where_trusted(fused: np.ndarray, motion: np.ndarray,
                         weight: np.ndarray) -> np.ndarray:
    """The motion method's frames where its guard trusts them whole (weight 1), the fused
    frames where it fell back (weight 0), blended by the weight in between: the fused method
    beyond the thresholds at which its network saw motion frames
    (:data:`~trmd_cli.models.fusion.MAX_CONTRAST`). Where the weight is 0 its input is EDI's
    frames, as on the still cameras of its training set, which reach higher thresholds.

    Args:
        fused, motion: (2N+1, H, W[, 3]) float32, the fused frames and the motion method's.
        weight: (2N+1, H, W) float32 [0, 1], the motion deconvolution's share in its frames.
    Returns:
        (2N+1, H, W[, 3]) float32.
    """
    w = weight[..., None] if fused.ndim == 4 else weight
    return (fused + w * (motion - fused)).astype(np.float32)
