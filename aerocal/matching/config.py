"""Configuration of feature extraction, matching, verification and track building."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: Tile origins are multiples of this many pixels: SIFT's octave o samples every 2**o-th pixel of the
#: (precisely upscaled) image, so tiles starting on a multiple of 32 see the same pyramid grid as the
#: whole image for octaves 0..5 and their keypoints land where the untiled detector puts them.
TILE_ALIGN = 32


@dataclass(frozen=True)
class FeatureConfig:
    """SIFT detection on image tiles (OpenCV ``cv2.SIFT``), with a per-image cap.

    Attributes
    ----------
    max_features:
        Per-image cap: the strongest keypoints by SIFT response are kept (default 8000; 0 = no cap).
    tile_size:
        Side of the square tiles, pixels (default 1024; 0 = detect on the whole image). A 640x512
        thermal frame is one tile; a 20 MP frame is 6 x 4 tiles.
    tile_overlap:
        Overlap of neighbouring tiles, pixels (default 64). Each tile owns the keypoints in its core
        (the tile minus half the overlap on every interior side), so a keypoint in an overlap is kept
        once, from the tile where it is farthest from a border. ``tile_size - tile_overlap`` must be a
        multiple of :data:`TILE_ALIGN` (32).
    n_octave_layers, contrast_threshold, edge_threshold, sigma:
        OpenCV SIFT parameters (defaults 3, 0.04, 10, 1.6: OpenCV's, i.e. Lowe's). Lower
        ``contrast_threshold`` gives more keypoints on low-contrast frames.
    precise_upscale:
        OpenCV's ``enable_precise_upscale`` (default True). With OpenCV's default upscaling the keypoints
        sit 0.25 px right of and below the image content (measured on an H20T frame and its mirror
        image: x + x' = W - 0.5 in OpenCV coordinates instead of W - 1); with it they are unbiased.
    fine_octave_max_pixels:
        Frames of at most this many pixels (default 12 MP) are detected as OpenCV does, from an octave -1 it
        makes by upsampling the frame twice; larger frames from octave 0, the frame itself, as COLMAP's
        ``first_octave=0`` does (OpenCV has no such setting: the tile is reduced twice by area averaging, OpenCV
        upsamples it back to the frame's grid, and the keypoints are scaled back). The upsampled octave holds
        three quarters of SIFT's pixels: a 20 MP frame is searched as 80 MP. Without it detection is several
        times faster and verifies more inliers, but each keypoint is coarser and the self-calibration's formal
        sigmas grow (``benchmarks/RESULTS.md``, "SIFT from octave 0 on visible frames"). The default is a
        judgement, not a measured crossover: it keeps octave -1, and the finer keypoints, for every thermal
        camera and for visible frames of up to 12 MP (the shared 2-3 MP visible sets among them), and spares only
        larger frames, where octave -1 would search 50 MP or more per frame. 0 detects every frame from octave 0.
    granularity:
        Unit of parallel work on a Dask cluster: ``"image"`` (one task loads, tiles and detects one
        image), ``"tile"`` (one task per tile, the loaded image shared through the cluster; for a few
        large images), or ``"auto"`` (default: tiles when there are fewer than two images per worker).
    """

    max_features: int = 8000
    tile_size: int = 1024
    tile_overlap: int = 64
    n_octave_layers: int = 3
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    precise_upscale: bool = True
    fine_octave_max_pixels: int = 12_000_000
    granularity: Literal["auto", "image", "tile"] = "auto"

    def __post_init__(self) -> None:
        if self.max_features < 0:
            raise ValueError(f"FeatureConfig.max_features must be >= 0, got {self.max_features}")
        if self.tile_size:
            size, overlap = self.tile_size, self.tile_overlap
            if size < 2 * TILE_ALIGN:
                raise ValueError(f"FeatureConfig.tile_size must be 0 or >= {2 * TILE_ALIGN}, got {size}")
            if not 0 <= overlap < size:
                raise ValueError(f"FeatureConfig.tile_overlap must be in [0, tile_size), got {overlap}")
            if (size - overlap) % TILE_ALIGN:
                raise ValueError(
                    f"FeatureConfig: tile_size - tile_overlap = {size - overlap} must be a multiple of "
                    f"{TILE_ALIGN} (e.g. tile_size=1024, tile_overlap=64)"
                )
        if self.fine_octave_max_pixels < 0:
            raise ValueError(f"FeatureConfig.fine_octave_max_pixels must be >= 0, got {self.fine_octave_max_pixels}")
        if self.granularity not in ("auto", "image", "tile"):
            raise ValueError(
                f"FeatureConfig.granularity {self.granularity!r} unknown; valid: auto, image, tile"
            )


@dataclass(frozen=True)
class MatchConfig:
    """Descriptor matching, geometric verification and tracks.

    Attributes
    ----------
    ratio:
        Lowe's ratio test, applied in both directions (default 0.8).
    mutual:
        Keep only mutual nearest neighbours (default True).
    matcher:
        ``"exact"`` (default): true nearest neighbours by brute force, the squared distances of all
        descriptor pairs from one float32 matrix product (BLAS). ``"flann"``: OpenCV FLANN randomised
        KD-trees, approximate. Exact is the default because it was faster than FLANN at the feature counts of
        aerial frames and finds nearly all of FLANN's matches and slightly more in all
        (``benchmarks/history/engine_measurements.md``).
    flann_trees, flann_checks:
        FLANN forest size and leaves checked per query (defaults 4 and 64; ``matcher="flann"`` only).
    seed:
        Seed of OpenCV's random generator (``cv2.setRNGSeed``, the calling thread's generator) before
        every FLANN index is built, so that matches are reproducible and do not depend on which worker
        ran them (default 0; ``matcher="flann"`` only: the exact matcher has no randomness).
    geometry:
        ``"fundamental"`` (default; any scene) or ``"homography"`` (nadir views of flat terrain).
    ransac_threshold:
        Inlier threshold, pixels (default 1.0): MAGSAC++'s maximum noise scale for the fundamental
        matrix, the transfer error for the homography.
    ransac_confidence, ransac_max_iters:
        RANSAC confidence (default 0.9999) and iteration cap (default 10000).
    min_matches:
        Pairs with fewer putative matches are not verified; pairs with fewer inliers are dropped
        (default 15).
    pairs_per_task:
        Pairs matched by one Dask task (default 4). A task's overhead is small against matching a pair: small
        batches keep the workers evenly loaded (with ``matcher="flann"`` an image's index is built once per
        batch).
    sigma_px:
        A-priori standard deviation of a tie-point measurement written into the observations, pixels
        (default 0.5).
    min_track_length:
        Tracks seen in fewer images are dropped (default 2).
    """

    ratio: float = 0.8
    mutual: bool = True
    matcher: Literal["exact", "flann"] = "exact"
    flann_trees: int = 4
    flann_checks: int = 64
    seed: int = 0
    geometry: Literal["fundamental", "homography"] = "fundamental"
    ransac_threshold: float = 1.0
    ransac_confidence: float = 0.9999
    ransac_max_iters: int = 10000
    min_matches: int = 15
    pairs_per_task: int = 4
    sigma_px: float = 0.5
    min_track_length: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"MatchConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.matcher not in ("exact", "flann"):
            raise ValueError(f"MatchConfig.matcher {self.matcher!r} unknown; valid: exact, flann")
        if self.geometry not in ("fundamental", "homography"):
            raise ValueError(
                f"MatchConfig.geometry {self.geometry!r} unknown; valid: fundamental, homography"
            )
        if self.ransac_threshold <= 0:
            raise ValueError(f"MatchConfig.ransac_threshold must be > 0 px, got {self.ransac_threshold}")
        if self.min_matches < 8:
            raise ValueError(f"MatchConfig.min_matches must be >= 8, got {self.min_matches}")
        if self.pairs_per_task < 1:
            raise ValueError(f"MatchConfig.pairs_per_task must be >= 1, got {self.pairs_per_task}")
        if self.sigma_px <= 0:
            raise ValueError(f"MatchConfig.sigma_px must be > 0, got {self.sigma_px}")
        if self.min_track_length < 2:
            raise ValueError(f"MatchConfig.min_track_length must be >= 2, got {self.min_track_length}")
