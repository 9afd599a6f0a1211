"""The optical-flow option table: what each ``flow_preset`` name means, checked without
importing OpenCV, numba or torch (the configuration validates a preset name with it; the
computation lives in ``flow.py``).

Options (measured in docs/flow.md, ``python -m bench.flow``):

* ``tracked`` (the default): an 8 x 8 grid of points tracked frame by frame through the voxel
  with pyramidal Lucas-Kanade, bilinear between the points.
* ``tracked-g12``: the same with a 12 x 12 grid, for independently moving objects.
* ``ultrafast``: OpenCV DIS ultrafast between the two boundary frames (cheap; accurate only for
  small motion per voxel).
* ``raft-small``, ``raft-large``: torchvision's RAFT (the paper's choice) with local weights
  only; never downloaded.

Flow convention everywhere: pixels, ``(dx, dy)`` with ``a(x) ~ b(x + flow(x))``.
"""
from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

from v2v_server.checks import check_int

__all__ = [
    "DEFAULT_FLOW", "DIS_PRESETS", "DISParams", "FLOW_OPTIONS", "FlowOption", "FlowUnavailable", "TrackParams",
    "check_option", "load_raft", "raft_weight_places", "raft_weights", "unavailable_reason",
]

#: OpenCV DIS presets by name (``cv2.DISOPTICAL_FLOW_PRESET_*``).
DIS_PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}


class FlowUnavailable(RuntimeError):
    """The option needs something this machine lacks (RAFT weights or torchvision)."""


@dataclass(frozen=True)
class DISParams:
    """One OpenCV DIS configuration: a preset and optional overrides of its settings
    (Kroeger et al., ECCV 2016, OpenCV ``DISOpticalFlow``).

    Attributes:
        preset: "ultrafast", "fast" or "medium".
        finest_scale: finest pyramid level computed (0 = full resolution; a level coarser than
            the coarsest one OpenCV builds for the frame size is clamped to it).
        patch_size, patch_stride: pixels.
        gd_iterations: gradient-descent iterations per patch.
        vr_iterations: variational refinement iterations (0 = off).

    Raises:
        ValueError: naming the setting, for an unknown preset or a bad value.
    """

    preset: str = "medium"
    finest_scale: Optional[int] = None
    patch_size: Optional[int] = None
    patch_stride: Optional[int] = None
    gd_iterations: Optional[int] = None
    vr_iterations: Optional[int] = None

    def __post_init__(self):
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"DIS preset must be one of {list(DIS_PRESETS)}, got {self.preset!r}")
        for name in ("finest_scale", "patch_size", "patch_stride", "gd_iterations", "vr_iterations"):
            v = getattr(self, name)
            low = 1 if name in ("patch_size", "patch_stride", "gd_iterations") else 0
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < low):
                raise ValueError(f"DIS {name} must be an integer >= {low} or None, got {v!r}")


@dataclass(frozen=True)
class TrackParams:
    """Settings of a ``tracked`` option: a ``grid`` x ``grid`` lattice of points over the crop
    (corners and borders included) tracked with OpenCV pyramidal Lucas-Kanade
    (``calcOpticalFlowPyrLK``; Bouguet 2001, "Pyramidal implementation of the Lucas Kanade
    feature tracker").

    Attributes:
        grid: points per side (>= 2); the dense flow is bilinear between them, so it resolves
            motion at about ``crop / (grid - 1)`` px.
        window: LK window side, px (odd, >= 3).
        levels: pyramid levels above full resolution for a pair searched from zero (the first
            pair of each voxel, and the pair after a pause); each level doubles the motion
            found, about ``window / 2 * 2**levels`` px per frame.
        prior_levels: pyramid levels for a pair started from the point's previous one-frame
            motion (constant-velocity prediction); points LK loses that way are searched again
            from zero with ``levels``.
        iterations, eps: LK stopping rule per level (at most ``iterations``; or a step under
            ``eps`` px).
        zoom: scale change per frame, as ``|log s|``, above which pairs are tracked
            zoom-compensated (None: never). LK follows a translating window; when the view
            shrinks or grows by more than a few per cent per frame, the window's content
            changes scale and LK drifts or drops the point (a 5 % scale change per frame is
            1.28x per 5-frame voxel). A compensated pair resizes the second frame by the
            inverse of the scale predicted from the previous pair (a similarity fitted to its
            points' motion, ``tracking._zoom_fit``), starts LK from the positions the similarity
            predicts, searched over ``compensated_levels`` levels, and maps the points back.
            The scale is checked once per voxel, on the pair that moves the points off the
            grid (entering: that pair is tracked again, compensated by its own fit, and kept
            if the fit explains the points' motion as a whole, ``tracking.ZOOM_INLIERS``); while
            compensated, on every pair, and the mode carries into the next voxel while the
            scale change stays above ``zoom``.
        compensated_levels: pyramid levels above full resolution for a compensated pair (the
            motion left after the prediction is small).

    Raises:
        ValueError: naming the setting, for a bad value.
    """

    grid: int = 8
    window: int = 9
    levels: int = 2
    prior_levels: int = 0
    iterations: int = 5
    eps: float = 0.03
    zoom: Optional[float] = 0.05
    compensated_levels: int = 0

    def __post_init__(self):
        for name, low in (("grid", 2), ("window", 3), ("levels", 0), ("prior_levels", 0), ("iterations", 1),
                          ("compensated_levels", 0)):
            check_int(f"tracking {name}", getattr(self, name), low)
        if self.window % 2 == 0:
            raise ValueError(f"tracking window must be odd, got {self.window}")
        if not (isinstance(self.eps, (int, float)) and self.eps > 0):
            raise ValueError(f"tracking eps must be a positive number (px), got {self.eps!r}")
        if self.zoom is not None and (isinstance(self.zoom, bool) or not isinstance(self.zoom, (int, float))
                                      or not self.zoom > 0):
            raise ValueError(f"tracking zoom must be None or a positive number (|log scale| per frame), "
                             f"got {self.zoom!r}")


@dataclass(frozen=True)
class FlowOption:
    """One way of computing a sample's flow (see the module doc).

    Attributes:
        name: the key in ``FLOW_OPTIONS`` (the config's ``flow_preset``).
        method: "direct" (DIS between the boundary frames), "tracked" or "raft".
        dis: direct only: the DIS settings.
        track: tracked only: the tracking settings.
        raft: raft only: "small" or "large".
        summary: one line for docs and logs.

    Raises:
        ValueError: naming the option, for an unknown method or settings of the wrong type.
    """

    name: str
    method: str
    dis: DISParams = DISParams()
    track: TrackParams = TrackParams()
    raft: str = "small"
    summary: str = ""

    def __post_init__(self):
        if self.method not in ("direct", "tracked", "raft"):
            raise ValueError(f"flow option {self.name!r}: method must be direct, tracked or raft, got {self.method!r}")
        if not isinstance(self.dis, DISParams):
            raise ValueError(f"flow option {self.name!r}: dis must be DISParams, got {self.dis!r}")
        if not isinstance(self.track, TrackParams):
            raise ValueError(f"flow option {self.name!r}: track must be TrackParams, got {self.track!r}")
        if self.raft not in ("small", "large"):
            raise ValueError(f"flow option {self.name!r}: raft must be small or large, got {self.raft!r}")


#: The one flow option table: the config's ``flow_preset`` names a key (docs/flow.md measures them).
FLOW_OPTIONS: Dict[str, FlowOption] = {o.name: o for o in (
    FlowOption("tracked", "tracked", track=TrackParams(grid=8),
               summary="an 8 x 8 grid of points tracked frame by frame with pyramidal Lucas-Kanade, bilinear between them"),
    FlowOption("tracked-g12", "tracked", track=TrackParams(grid=12),
               summary="as tracked with a 12 x 12 grid (finer: independently moving objects; 1.7x the cost)"),
    FlowOption("ultrafast", "direct", DISParams("ultrafast"),
               summary="DIS ultrafast between the voxel's boundary frames (cheap; small motion only)"),
    FlowOption("raft-small", "raft", raft="small", summary="torchvision RAFT small at the voxel spacing (local weights only)"),
    FlowOption("raft-large", "raft", raft="large", summary="torchvision RAFT large at the voxel spacing (local weights only)"),
)}

#: The option samples use unless ``flow_preset`` says otherwise (chosen in docs/flow.md).
DEFAULT_FLOW = "tracked"


def check_option(name) -> FlowOption:
    """The option called ``name`` (case-insensitive).

    Raises:
        ValueError: naming ``flow_preset`` and the known options, for an unknown name.
    """
    key = str(name).lower()
    if key not in FLOW_OPTIONS:
        raise ValueError(f"flow_preset must be one of {list(FLOW_OPTIONS)}, got {name!r}")
    return FLOW_OPTIONS[key]


def raft_weights(size: str = "small") -> Optional[Path]:
    """Path of local RAFT weights for torchvision's ``raft_<size>``, or None.

    Looks at ``$V2V_RAFT_WEIGHTS`` (a ``.pth`` state dict), then torchvision's cache
    (``$TORCH_HOME/hub/checkpoints/raft_<size>*.pth``). Never downloads.
    """
    place = raft_weight_places(size)[0]
    if "*" not in place.name:
        return place if place.is_file() else None
    hits = sorted(place.parent.glob(place.name))
    return hits[0] if hits else None


def raft_weight_places(size: str = "small") -> List[Path]:
    """Where :func:`raft_weights` looks: ``[$V2V_RAFT_WEIGHTS]`` when set, else the pattern
    ``[$TORCH_HOME/hub/checkpoints/raft_<size>*.pth]`` (``TORCH_HOME`` defaulting to
    ``~/.cache/torch``)."""
    env = os.environ.get("V2V_RAFT_WEIGHTS")
    if env:
        return [Path(env)]
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    return [home / "hub" / "checkpoints" / f"raft_{size}*.pth"]


def load_raft(size: str, weights: Optional[str] = None):
    """torchvision's ``raft_small`` or ``raft_large`` network (Teed & Deng, ECCV 2020) with
    local weights, in eval mode on the CPU, its parameters frozen: the one loader of the server's
    ``raft-*`` flow options and the trainer's ``loss.flow_source: raft-*``.

    Args:
        size: "small" or "large".
        weights: a ``.pth`` state dict; None: the first file of :func:`raft_weight_places`.

    Returns:
        the ``torch.nn.Module``; ``net(img1, img2, num_flow_updates=k)`` takes (N, 3, H, W)
        float images in [-1, 1] with H, W multiples of 8 and returns a list of (N, 2, H, W)
        flows in pixels, the last the finest.

    Raises:
        ValueError: ``size`` is neither "small" nor "large".
        FlowUnavailable: torchvision cannot be imported; no weight file (the message lists the
            places looked at; weights are never downloaded); the file is not a ``raft_<size>``
            state dict.
    """
    if size not in ("small", "large"):
        raise ValueError(f"RAFT size must be small or large, got {size!r}")
    try:
        import torch
        from torchvision.models import optical_flow
    except ImportError as e:
        raise FlowUnavailable(f"RAFT needs torchvision (the build matching the installed torch), which cannot be "
                              f"imported ({e})") from e
    places = [Path(weights)] if weights else raft_weight_places(size)
    path = (places[0] if places[0].is_file() else None) if weights else raft_weights(size)
    if path is None:
        raise FlowUnavailable(
            f"no local RAFT {size} weights; looked at {', '.join(str(p) for p in places)}. Save torchvision's "
            f"raft_{size} state dict there (or set V2V_RAFT_WEIGHTS); weights are never downloaded")
    net = getattr(optical_flow, f"raft_{size}")(weights=None)
    try:
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    except Exception as e:
        raise FlowUnavailable(f"{path} is not a raft_{size} state dict: {e}") from e
    net.requires_grad_(False)
    return net.eval()


def unavailable_reason(name) -> Optional[str]:
    """Why option ``name`` cannot run on this machine (RAFT without torchvision or local
    weights), or None when it can. Loads nothing.

    Raises:
        ValueError: for an unknown option name.
    """
    o = check_option(name)
    if o.method != "raft":
        return None
    try:
        if importlib.util.find_spec("torchvision") is None:
            return "RAFT needs torchvision, which is not installed"
    except (ImportError, ValueError):
        return "RAFT needs torchvision, which cannot be imported"
    if raft_weights(o.raft) is None:
        return (f"no local RAFT {o.raft} weights (set V2V_RAFT_WEIGHTS or put raft_{o.raft}*.pth in "
                f"torchvision's cache); they are never downloaded")
    return None
