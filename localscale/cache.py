"""Feature cache for many pairs: encode each image once, pair it many times.

Backbone+ASPP features dominate the cost of a pair; the heads are cheap. For image
collections (every image against many others) :class:`FeatureCache` keeps encodings in
an LRU bounded by bytes, and :func:`predict_pairs` runs the heads batched.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path
from typing import Iterable, Iterator

import torch
import torch.nn.functional as F

from .core.errors import LocalScaleError
from .io.preprocess import letterbox, to_tensor
from .models.base import EncodedImage, ScaleModel


class FeatureCache:
    """LRU cache of :class:`EncodedImage` keyed by file path (+ mtime), bounded by ``max_bytes``."""

    def __init__(self, model: ScaleModel, max_bytes: int = 256 * 2**20, bf16: bool = False):
        self.model, self.max_bytes, self.bf16 = model, max_bytes, bf16
        self._items: OrderedDict[tuple, EncodedImage] = OrderedDict()
        self.bytes = 0
        self.hits = self.misses = 0

    @staticmethod
    def key(path: str | os.PathLike) -> tuple:
        p = Path(os.path.realpath(os.path.abspath(path)))  # never raises on a symbolic link loop
        try:
            return (str(p), p.stat().st_mtime_ns)
        except OSError:
            return (str(p), None)

    def __contains__(self, path) -> bool:
        return self.key(path) in self._items

    def __len__(self) -> int:
        return len(self._items)

    def get_many(self, paths: list) -> list[EncodedImage]:
        """Encodings of ``paths`` (missing ones are encoded together, as one batch)."""
        keys = [self.key(p) for p in paths]
        found = {}
        for k in keys:
            if k in self._items:
                self._items.move_to_end(k)
                found[k] = self._items[k]
                self.hits += 1
        todo = list(dict.fromkeys(k for k in keys if k not in found))
        if todo:
            self.misses += len(todo)
            for k, e in zip(todo, encode_batch(self.model, [k[0] for k in todo], self.bf16)):
                found[k] = e
                self._put(k, e)
        return [found[k] for k in keys]

    def get(self, path) -> EncodedImage:
        return self.get_many([path])[0]

    def _put(self, k: tuple, e: EncodedImage) -> None:
        self._items[k] = e
        self.bytes += e.nbytes
        while self.bytes > self.max_bytes and len(self._items) > 1:
            _, old = self._items.popitem(last=False)
            self.bytes -= old.nbytes


@torch.inference_mode()
def encode_batch(model: ScaleModel, images: list, bf16: bool = False) -> list[EncodedImage]:
    """Encode several images (paths or arrays) in one backbone pass."""
    tensors, boxes = [], []
    for im in images:
        rgb, shape = model.load(im, name="image")  # a file's messages name its path once
        boxed, lb = letterbox(rgb, model.config.image_size, shape)
        tensors.append(to_tensor(boxed))
        boxes.append(lb)
    with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
        feats = model.encode(torch.stack(tensors).to(model.device)).float()
    return [EncodedImage(f[None], lb) for f, lb in zip(feats, boxes)]


@torch.inference_mode()
def predict_batch(
    model: ScaleModel,
    encs_a: list[EncodedImage],
    encs_b: list[EncodedImage],
    bf16: bool = False,
    hard: bool = False,
    planar: bool = False,
):
    """Run the model's head on a batch of encoded pairs; returns one prediction per pair.

    ``hard`` / ``planar``: read-out options of :meth:`LocalScaleNet.predict` (ignored for ScaleNet)."""
    fa = torch.cat([e.features for e in encs_a])
    fb = torch.cat([e.features for e in encs_b])
    local = hasattr(model, "forward_features_all")
    with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
        if local:  # A's self-correlation terms: once per encoding, kept with it
            terms = [model.cached_self_terms(e, bf16) for e in encs_a]
            top = None if terms[0][1] is None else torch.cat([t[1] for t in terms])
            out = model.forward_features_all(fa, fb, (torch.cat([t[0] for t in terms]), top))
        else:
            out = model.forward_features(fa, fb)
    if not local:  # global ScaleNet: both directions
        pa, pb = F.softmax(out[0].float(), 1), F.softmax(out[1].float(), 1)
        return [model._readout(pa[i], pb[i], a.letterbox, b.letterbox) for i, (a, b) in enumerate(zip(encs_a, encs_b))]
    probs = F.softmax(out[0].float(), 1)
    visible = torch.sigmoid(out[1].float())[:, 0] if out[1] is not None else None
    return [
        model._readout(probs[i], a.letterbox, b.letterbox, hard, planar, visible[i] if visible is not None else None)
        for i, (a, b) in enumerate(zip(encs_a, encs_b))
    ]


def predict_pairs(
    model: ScaleModel,
    pairs: Iterable[tuple],
    cache: FeatureCache | None = None,
    batch_size: int = 8,
    hard: bool = False,
    planar: bool = False,
) -> Iterator[tuple[tuple, object]]:
    """Yield ``(pair, prediction)`` for each ``(path_a, path_b)``, in input order;
    a bad pair yields ``(pair, LocalScaleError)`` and the others are still processed.

    ``cache``: encodings to reuse (and its ``bf16`` setting); a new one when None.
    ``hard`` / ``planar``: read-out options as in :meth:`LocalScaleNet.predict`.
    """
    if cache is None:  # an empty cache is falsy (it has __len__), so test for None
        cache = FeatureCache(model)
    chunk: list[tuple] = []

    def flush():
        results: list = [None] * len(chunk)
        good, encs = [], []
        for i, pair in enumerate(chunk):
            try:
                encs.append(cache.get_many(list(pair)))
                good.append(i)
            except LocalScaleError as e:
                results[i] = e
        if good:
            preds = predict_batch(model, [e[0] for e in encs], [e[1] for e in encs], cache.bf16, hard, planar)
            for i, pred in zip(good, preds):
                results[i] = pred
        yield from zip(chunk, results)

    for pair in pairs:
        chunk.append(tuple(pair))
        if len(chunk) == batch_size:
            yield from flush()
            chunk = []
    if chunk:
        yield from flush()
