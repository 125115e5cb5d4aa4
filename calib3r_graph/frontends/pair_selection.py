"""Which pairs of views the pairwise frontend matches, without trying every pair.

Two-view geometry costs about 0.1 s a pair at 640x480 (a 4000x4000 descriptor product, RANSAC, the
guided pass), so trying all N(N-1)/2 pairs grows quadratically: 1485 pairs for 55 images, most of
which see too little of the same scene to verify. Each view is matched instead with the partners
most likely to overlap, by two cheap cues that are independent of each other:

- **the image**: a VLAD descriptor (Jegou et al. 2010) of the RootSIFT features already
  extracted, over a 64-word vocabulary k-means learns from this recording's own descriptors (no
  trained model; 64 words is within the 16-256 that paper found to retrieve views of one scene
  well, and costs 64 x 128 numbers a view); the similarity of two views is the dot product of their (power- and L2-normalised)
  descriptors;
- **the robot**, for views of the same camera: the relative rotation angle of the two flanges
  equals the cameras' whatever ``ee_T_cam`` is (rotation angles are invariant under conjugation),
  and the flanges' distance bounds the cameras' within ``2 |t_X|``; views a small rotation and a
  short move apart see the scene from nearly the same viewpoint. The two are ranked separately
  and the ranks added, so neither needs a scale.

Per view, the ``partners`` best of the two rankings, taken alternately, are matched; with a
maximum spanning tree over the image similarity (the candidate graph is connected) and, for a
rig, every same-frame pair. After the first round, :meth:`PairSelection.more` names the next
partners of the views the verified pairs connect weakly, and pairs between the parts of a graph
the first round left apart. Each round adds at most ``partners`` pairs per view: the pairs, and
the time, grow linearly with the number of views; the similarities themselves are one small
product per pair (64 x 128 numbers).
"""

import cv2
import numpy as np
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from calib3r_graph.io.predictions import split_view_id

VLAD_WORDS = 64
VOCABULARY_SAMPLE = 20000  # descriptors k-means learns from (k-means' cost grows with this, not with N)


def vocabulary(descs: list, seed=0) -> np.ndarray | None:
    """(words, 128) k-means centres learnt from (a sample of) N images' descriptors; None if they have none."""
    nonempty = [d for d in descs if len(d)]
    if not nonempty:
        return None
    rng = np.random.default_rng(seed)
    pool = np.concatenate(nonempty).astype(np.float32)
    if len(pool) > VOCABULARY_SAMPLE:
        pool = pool[rng.choice(len(pool), VOCABULARY_SAMPLE, replace=False)]
    words = min(VLAD_WORDS, len(pool))
    cv2.setRNGSeed(seed)  # k-means++ seeding draws from OpenCV's (per-thread) generator
    _, _, centres = cv2.kmeans(pool, words, None, (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 20, 1e-4), 1,
                               cv2.KMEANS_PP_CENTERS)
    return centres


def vlad(descs: list, seed=0, centres=None) -> np.ndarray:
    """(N, VLAD_WORDS * 128) unit VLAD descriptors of N images' RootSIFT descriptors (each (n_i, 128)),
    over ``centres`` (:func:`vocabulary`; learnt from ``descs`` when None)."""
    out = np.zeros((len(descs), VLAD_WORDS * 128), np.float32)
    centres = vocabulary(descs, seed) if centres is None else centres
    if centres is None:
        return out
    c2 = (centres * centres).sum(1)
    for i, d in enumerate(descs):
        if not len(d):
            continue
        d = np.asarray(d, np.float32)
        word = np.argmin(c2[None] - 2 * d @ centres.T, axis=1)
        v = np.zeros((VLAD_WORDS, 128), np.float32)
        np.add.at(v, word, d - centres[word])
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)  # intra-normalisation
        v = np.sign(v) * np.sqrt(np.abs(v))  # power normalisation
        out[i] = v.ravel() / max(np.linalg.norm(v), 1e-12)
    return out


# Flange rotations and distances closer than these tie in the robot ranking (:func:`_tied`): below
# what an arm repeats (about 0.01 deg and 0.02-0.1 mm) a difference says nothing of how two
# viewpoints overlap, and ranking by it lets a recording's noise pick the partners. rwhe_kuka_1 moves
# at one orientation for its first 12 poses (their rotations differ by 1e-5 rad) and on a grid (its
# distances tie to 1e-6 m): its poses written with four decimals in mm and degrees (as a KUKA shows
# them, 8e-5 mm / 8e-5 deg off) took 11 pairs that its 154 did not and left 14 of them, and solve's
# result moved by 0.58 mm, 0.87 sigma. Now none differ there, nor on rwhe_kuka_2 and tabb_ds1.
ROTATION_RESOLUTION_DEG = 0.01
DISTANCE_RESOLUTION_M = 1e-4


def _tied(x: np.ndarray, tol: float) -> np.ndarray:
    """Each row's values as group numbers (0 = smallest) where values that a chain of gaps of at most
    ``tol`` joins share one: ties that no fixed rounding grid would split at its cell borders."""
    order = np.argsort(x, axis=1, kind="stable")
    xs = np.take_along_axis(x, order, axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf: the same group
        step = np.diff(xs, axis=1) > tol
    groups = np.concatenate([np.zeros((len(x), 1), int), np.cumsum(step, axis=1)], axis=1)
    out = np.empty_like(groups)
    np.put_along_axis(out, order, groups, axis=1)
    return out


def _ranks(x: np.ndarray) -> np.ndarray:
    """Rank of each entry of each row (0 = smallest), ties in order."""
    return np.argsort(np.argsort(x, axis=1, kind="stable"), axis=1, kind="stable")


class PairSelection:
    """The candidate pairs of a set of views, round by round (see the module's docstring)."""

    def __init__(self, vids: list, descs: dict, base_T_ee: dict, partners: int, seed=0, vlads=None):
        """``vlads``: the views' (N, D) VLAD descriptors when the caller has them (a live session
        keeps them per view); otherwise :func:`vlad` of ``descs``."""
        self.vids = list(vids)
        self.partners = partners
        n = len(self.vids)
        cams = [split_view_id(v)[0] for v in self.vids]
        frames = [split_view_id(v)[1] for v in self.vids]
        V = vlad([descs[v] for v in self.vids], seed) if vlads is None else np.asarray(vlads, np.float32)
        self.similarity = V @ V.T
        np.fill_diagonal(self.similarity, -np.inf)
        # robot: relative rotation angle and distance of the flanges, same camera only
        R = np.array([base_T_ee[f].rotation().matrix() for f in frames])
        t = np.array([base_T_ee[f].translation() for f in frames])
        cos = (np.einsum("aij,bij->ab", R, R) - 1) / 2
        angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        dist = np.linalg.norm(t[:, None] - t[None], axis=2)
        same_cam = np.array(cams)[:, None] == np.array(cams)[None]
        robot = np.where(same_cam, 0.0, np.inf)
        robot = (robot + _ranks(_tied(np.where(same_cam, angle, np.inf), ROTATION_RESOLUTION_DEG))
                 + _ranks(_tied(np.where(same_cam, dist, np.inf), DISTANCE_RESOLUTION_M)))
        np.fill_diagonal(robot, np.inf)
        # Per view, its partners in order: the two rankings alternately, each partner once.
        by_image = np.argsort(-self.similarity, axis=1, kind="stable")
        by_robot = np.argsort(robot, axis=1, kind="stable")
        self.order = []
        for i in range(n):
            robot_list = [j for j in by_robot[i] if np.isfinite(robot[i, j])]
            image_list = [j for j in by_image[i] if j != i]
            seen, merged = set(), []
            for k in range(max(len(robot_list), len(image_list))):
                for lst in (robot_list, image_list):
                    if k < len(lst) and lst[k] not in seen:
                        seen.add(lst[k])
                        merged.append(lst[k])
            self.order.append(merged)
        self.rig = {self._pair(i, j) for i in range(n) for j in range(i + 1, n)
                    if frames[i] == frames[j] and cams[i] != cams[j]}

    def _pair(self, i, j):
        return (self.vids[i], self.vids[j]) if i < j else (self.vids[j], self.vids[i])

    def picks(self, vid) -> list:
        """The pairs ``vid`` picks itself in the first round: its ``partners`` best partners and, for a
        rig, its same-frame pairs (a live session adds the new view's picks only)."""
        i = self.vids.index(vid)
        own = {self._pair(i, j) for j in self.order[i][:self.partners]} if self.partners > 0 else set()
        return sorted(own | {p for p in self.rig if vid in p})

    def chosen_by(self, vid) -> list:
        """The first round's pairs of ``vid`` that the other views pick (``vid`` is among their
        ``partners`` best): with :meth:`picks`, every first-round pair with ``vid`` but the spanning tree's."""
        i = self.vids.index(vid)
        if self.partners <= 0:
            return []
        return sorted(self._pair(i, j) for j in range(len(self.vids)) if j != i and i in self.order[j][:self.partners])

    def rank(self, vid) -> dict:
        """{partner view: its place in ``vid``'s partner order}."""
        i = self.vids.index(vid)
        return {self.vids[j]: r for r, j in enumerate(self.order[i])}

    def all_pairs(self) -> list:
        n = len(self.vids)
        return [self._pair(i, j) for i in range(n) for j in range(i + 1, n)]

    def first(self) -> list:
        """The first round's pairs (every pair when ``partners`` is 0 or covers all views)."""
        n = len(self.vids)
        if self.partners <= 0 or self.partners >= n - 1:
            return self.all_pairs()
        pairs = set(self.rig)
        for i in range(n):
            pairs.update(self._pair(i, j) for j in self.order[i][:self.partners])
        # connectivity: a maximum spanning tree over the image similarity
        W = np.where(np.isfinite(self.similarity), 2.0 - self.similarity, 0.0)  # > 0 off the diagonal
        tree = minimum_spanning_tree(W).tocoo()
        pairs.update(self._pair(i, j) for i, j in zip(tree.row, tree.col))
        return sorted(pairs)

    def more(self, tried, kept, weak_below: int) -> list:
        """Untried pairs for the next round: for each view with fewer than ``weak_below`` kept pairs,
        its next ``partners`` partners; for each part of the kept pairs' graph apart from the
        largest, its ``partners`` most similar untried pairs to the rest."""
        if self.partners <= 0:
            return []
        tried = set(tried)
        index = {v: i for i, v in enumerate(self.vids)}
        count = np.zeros(len(self.vids), int)
        for a, b in kept:
            count[index[a]] += 1
            count[index[b]] += 1
        new = set()
        for i in np.flatnonzero(count < weak_below):
            fresh = [j for j in self.order[i] if self._pair(i, j) not in tried]
            new.update(self._pair(i, j) for j in fresh[:self.partners])
        A = np.zeros((len(self.vids),) * 2)
        for a, b in kept:
            A[index[a], index[b]] = 1
        n_comp, label = connected_components(A, directed=False)
        if n_comp > 1:
            largest = np.bincount(label).argmax()
            for c in range(n_comp):
                if c == largest:
                    continue
                inside, outside = np.flatnonzero(label == c), np.flatnonzero(label != c)
                S = self.similarity[np.ix_(inside, outside)]
                cand = [(S[a, b], self._pair(inside[a], outside[b])) for a, b in zip(*np.unravel_index(
                    np.argsort(-S, axis=None), S.shape))]
                cand = [p for _, p in cand if p not in tried][:self.partners]
                new.update(cand)
        return sorted(new - tried)
