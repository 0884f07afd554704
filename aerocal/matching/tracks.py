"""Tracks: verified pairwise matches joined into multi-image tie points.

Nodes are (image, keypoint); every verified match is an edge; a track is a connected component
(``scipy.sparse.csgraph.connected_components``, the vectorised form of union-find). A component that
holds two keypoints of one image is inconsistent (some match in it is wrong) and is dropped whole.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from aerocal import tables
from aerocal.matching.config import MatchConfig


def _node_key(image_id: np.ndarray, keypoint_id: np.ndarray) -> np.ndarray:
    return (np.asarray(image_id, dtype=np.int64) << 32) | np.asarray(keypoint_id, dtype=np.int64)


def build_tracks(matches: pa.Table, keypoints: pa.Table, config: MatchConfig | None = None) -> pa.Table:
    """Join verified pairwise matches into multi-image tracks: the ``observations`` table.

    Every observation is a keypoint's position with ``sigma = config.sigma_px``. Tracks seen in fewer than
    ``config.min_track_length`` images, and tracks that contain two keypoints of the same image (some match in
    them is wrong), are dropped whole. ``track_id`` numbers the kept tracks 0..T-1 in the order of their smallest
    (image_id, keypoint_id); rows are sorted by track, then image.

    Args:
        matches: the ``matches`` table (:mod:`aerocal.tables`) of verified matches
            (:func:`aerocal.matching.match_pairs`).
        keypoints: the ``keypoints`` table the matches were made from; it gives each observation's position.
        config: ``sigma_px`` (pixels) and ``min_track_length`` (default :class:`MatchConfig`: 0.5 px, 2 images).

    Returns:
        The ``observations`` table: ``image_id``, ``track_id``, ``x``, ``y`` (the keypoint's position, pixels with
        the origin at the top-left corner of the top-left pixel, x right, y down) and ``sigma`` (pixels); empty
        when ``matches`` is.

    Raises:
        SchemaError: ``matches`` or ``keypoints`` does not match its :mod:`aerocal.tables` schema.
        ValueError: matches refer to keypoints absent from ``keypoints``; the message names a few
            (image_id, keypoint_id).
    """
    config = config or MatchConfig()
    m = tables.validate(matches, "matches")
    kp = tables.validate(keypoints, "keypoints")
    a = _node_key(m.column("image_id1").to_numpy(), m.column("keypoint_id1").to_numpy())
    b = _node_key(m.column("image_id2").to_numpy(), m.column("keypoint_id2").to_numpy())
    if len(a) == 0:
        return tables.empty("observations")
    nodes, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
    n = len(nodes)
    ea, eb = inv[: len(a)], inv[len(a) :]
    graph = coo_matrix((np.ones(len(ea), dtype=np.int8), (ea, eb)), shape=(n, n))
    _, label = connected_components(graph, directed=False)

    node_image = (nodes >> 32).astype(np.int64)
    # a component is consistent when no image appears twice in it
    order = np.lexsort((node_image, label))
    dup = (label[order][1:] == label[order][:-1]) & (node_image[order][1:] == node_image[order][:-1])
    bad = np.zeros(label.max() + 1, dtype=bool)
    bad[label[order][1:][dup]] = True
    size = np.bincount(label)
    keep_comp = ~bad & (size >= config.min_track_length)
    keep = keep_comp[label]

    # coordinates of the kept nodes
    kp_key = _node_key(kp.column("image_id").to_numpy(), kp.column("keypoint_id").to_numpy())
    kp_order = np.argsort(kp_key, kind="stable")
    pos = np.searchsorted(kp_key, nodes, sorter=kp_order)
    pos = np.minimum(pos, len(kp_key) - 1)
    found = kp_key[kp_order[pos]] == nodes
    if not found.all():
        missing = nodes[~found][:3]
        raise ValueError(
            f"matches refer to {int((~found).sum())} keypoint(s) absent from the keypoints table, e.g. "
            f"(image_id, keypoint_id) {[(int(k >> 32), int(k & 0xFFFFFFFF)) for k in missing]}; "
            "build the tracks from the keypoints table the matches were made from"
        )
    rows = kp_order[pos[keep]]
    x = kp.column("x").to_numpy()[rows].astype(np.float64)
    y = kp.column("y").to_numpy()[rows].astype(np.float64)

    # track ids 0..T-1 in the order of each component's smallest node (nodes are sorted)
    comp = label[keep]
    first = np.full(label.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, label, np.arange(n))
    kept_comps = np.nonzero(keep_comp)[0]
    rank = np.empty(label.max() + 1, dtype=np.int64)
    rank[kept_comps[np.argsort(first[kept_comps], kind="stable")]] = np.arange(len(kept_comps))
    track = rank[comp]
    image = node_image[keep]
    out_order = np.lexsort((image, track))
    return tables.from_columns("observations", {
        "image_id": image[out_order],
        "track_id": track[out_order],
        "x": x[out_order],
        "y": y[out_order],
        "sigma": np.full(len(out_order), config.sigma_px, dtype=np.float32),
    })
