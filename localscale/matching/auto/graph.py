"""The pair graph of a collection for ``correction="auto"``: what the verified pairs say about the
relation of their images (scale and quarter turn), composed into hypotheses for the pairs that did
not verify as they are.

A :class:`Relation` ``A -> B`` is the relation of :class:`~localscale.matching.Hypothesis`: turn B
by ``turn`` quarter turns, then content looks ``scale`` times bigger in B than in A. Relations
compose along paths: ``A -> X -> B`` multiplies the scales and adds the turns. In a collection a
close-up verified against one photo is then related to every photo that photo is related to, so
the pairs of the close-up with those photos get their hypothesis from the graph instead of from
the networks (each image needs a few levels and turns, each computed once: the cheap variant
of the paper's D-ScaleNet for collections).

Example::

    g = PairGraph()
    g.add("close.jpg", "photo1.jpg", Relation(0.25, 2, 80))
    g.add("photo1.jpg", "photo2.jpg", Relation(1.1, 0, 300))
    g.composed("close.jpg", "photo2.jpg")  # [Relation(0.275, 2, 80)]
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class Relation:
    """``S_{A->B} = scale`` after B is turned by ``turn`` quarter turns (counter-clockwise, as
    :func:`numpy.rot90`); ``strength``: the inliers that support it."""

    scale: float
    turn: int
    strength: int = 0

    def inverse(self) -> "Relation":
        """The relation ``B -> A``."""
        return Relation(1.0 / self.scale, (-self.turn) % 4, self.strength)

    def then(self, other: "Relation") -> "Relation":
        """``A -> C`` from ``self`` (``A -> B``) and ``other`` (``B -> C``)."""
        return Relation(self.scale * other.scale, (self.turn + other.turn) % 4, min(self.strength, other.strength))

    def is_identity(self, same_log2: float) -> bool:
        return self.turn % 4 == 0 and abs(math.log2(self.scale)) < same_log2

    def same_as(self, other: "Relation", same_log2: float) -> bool:
        return self.turn % 4 == other.turn % 4 and abs(math.log2(self.scale / other.scale)) < same_log2


class PairGraph:
    """Images as nodes, verified pairs as edges carrying their :class:`Relation` (one per pair: the
    strongest); connected components kept with union-find."""

    def __init__(self):
        self._edges: dict = {}  # (a, b) -> Relation a -> b, one direction stored
        self._adjacent: dict = {}
        self._parent: dict = {}

    def __len__(self) -> int:
        return len(self._edges)

    def add(self, a: str, b: str, relation: Relation) -> None:
        """Add (or strengthen) the edge ``a -> b``."""
        if not (math.isfinite(relation.scale) and relation.scale > 0):
            return
        old = self.relation(a, b)
        if old is not None and old.strength >= relation.strength:
            return
        self._edges.pop((b, a), None)
        self._edges[(a, b)] = relation
        self._adjacent.setdefault(a, set()).add(b)
        self._adjacent.setdefault(b, set()).add(a)
        ra, rb = self._root(a), self._root(b)
        if ra != rb:
            self._parent[ra] = rb

    def relation(self, a: str, b: str) -> Optional[Relation]:
        """The edge's relation ``a -> b`` (either stored direction), or None."""
        r = self._edges.get((a, b))
        if r is not None:
            return r
        r = self._edges.get((b, a))
        return None if r is None else r.inverse()

    def neighbours(self, a: str) -> set:
        return set(self._adjacent.get(a, ()))

    def _root(self, a: str) -> str:
        self._parent.setdefault(a, a)
        while self._parent[a] != a:
            self._parent[a] = self._parent[self._parent[a]]
            a = self._parent[a]
        return a

    def connected(self, a: str, b: str) -> bool:
        """Whether a path of verified pairs joins ``a`` and ``b``."""
        return self._root(a) == self._root(b)

    def composed(self, a: str, b: str, limit: int = 3, same_log2: float = 0.25) -> list:
        """Relations ``a -> b`` through one common neighbour, strongest first, at most ``limit``
        distinct ones (scales within ``same_log2`` and the same turn are one)."""
        found = []
        for x in sorted(self.neighbours(a) & self.neighbours(b)):
            found.append(self.relation(a, x).then(self.relation(x, b)))
        found.sort(key=lambda r: -r.strength)
        out: list = []
        for r in found:
            if not any(r.same_as(o, same_log2) for o in out):
                out.append(r)
            if len(out) >= limit:
                break
        return out


def relation_of(v, hypothesis) -> Optional[Relation]:
    """The relation a verified result's own geometry gives (else its ``hypothesis``'s; None if
    it did not verify)."""
    from .hypotheses import geometry_hypothesis

    if not v.verified:
        return None
    g = geometry_hypothesis(v)
    h = g if g is not None else hypothesis
    if h is None:
        return Relation(1.0, 0, int(v.num_inliers))
    return Relation(float(h.scale), int(h.turn) % 4, int(v.num_inliers))
