"""A skeleton from a lab's own keypoints and labelled frames (issue 28 item 1).

Labs draw their keypoints and a graph over them in their tool. :func:`read_keypoint_graph`
reads that definition from

* a DeepLabCut ``config.yaml``: ``bodyparts`` (multi-animal: ``multianimalbodyparts``; the
  ``uniquebodyparts`` are not the animal's) and ``skeleton`` (pairs of body parts);
* a SLEAP ``.slp`` (the skeleton in the ``metadata`` JSON) or a SLEAP skeleton ``.json``:
  nodes, edges of type 1 (body) and 2 (symmetry), as SLEAP's ``EdgeType`` numbers them;
* a DANNCE / Label3D skeleton ``.mat``: ``joint_names`` and ``joints_idx`` (1-based pairs,
  MATLAB's convention), MATLAB v5 (scipy) or v7.3 (HDF5, h5py);
* an anipose ``config.toml``: ``[triangulation] constraints`` (pairs kept at a fixed length).

:func:`skeleton_from_labels` turns it into an acm-rs :class:`~acm_rs.skeleton.Skeleton` with
the lab's triangulated labelled frames:

* the tree: where the graph is not a tree, the maximum spanning tree by rigidity (the edges
  whose length varies least over the labelled frames, coefficient of variation), a graph in
  pieces joined by the most rigid pairs between them; the root is the tree's centre (least
  eccentricity; ties by name). Dropped and added edges are reported;
* one joint per keypoint and one marker per keypoint at its joint (offset 0, bounded to 0:
  the keypoint *is* the joint); a leaf keypoint ends its bone;
* rest pose: the median shape of the Kabsch-aligned triangulated frames, each bone at its
  median labelled length, in a body frame (x = the animal's right from the left/right pairs,
  else the second principal axis; z = the long axis; y = z x x, ``up``);
* twist: with markers at the joints a bone's spin about itself is invisible, so one
  Rodrigues component per bone (the rest-pose axis closest to the bone) is fixed at 0; every
  bone direction stays reachable and the pose has 2 free entries per bone;
* left/right pairs: from the names (``left``/``right``, ``L``/``R`` tokens) and SLEAP's
  symmetry edges;
* joint limits: the range of each free component over the labelled poses widened by a margin
  (default 30 deg) on each side, none for the root bones (the animal's heading), or none.
"""

from __future__ import annotations

import json
import re
import tomllib
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import CameraRig
from .dlc import load_dlc_config
from .learning import triangulate
from .rotation import rodrigues
from .skeleton import Skeleton

__all__ = [
    "KeypointGraph",
    "KeypointTree",
    "LabSkeleton",
    "read_keypoint_graph",
    "rest_shape",
    "skeleton_from_labels",
    "spanning_tree",
    "symmetry_from_names",
]

#: Default widening (deg) of the labelled poses' angle ranges into joint limits.
LIMIT_MARGIN_DEG = 30.0


@dataclass
class KeypointGraph:
    """A lab's keypoint definition.

    Attributes
    ----------
    keypoints : list of str
    edges : list of (str, str)
        The lab's skeleton edges (any graph: cycles and pieces allowed).
    symmetry : list of (str, str)
        Left/right pairs the file declares (SLEAP symmetries); empty when it has none.
    source : str
        The file read.
    tool : str
        ``"deeplabcut"``, ``"sleap"``, ``"dannce"`` or ``"anipose"``.
    notes : list of str
        What was left out or changed while reading.
    """

    keypoints: list[str]
    edges: list[tuple[str, str]]
    symmetry: list[tuple[str, str]] = field(default_factory=list)
    source: str = ""
    tool: str = ""
    notes: list[str] = field(default_factory=list)


# -- readers ---------------------------------------------------------------------------------
def read_keypoint_graph(path: str | Path) -> KeypointGraph:
    """Read a lab's keypoints and skeleton from a DeepLabCut project or ``config.yaml``, a
    SLEAP ``.slp`` or skeleton ``.json``, a DANNCE/Label3D skeleton ``.mat`` or an anipose
    ``config.toml`` (chosen by the file's suffix; a folder means its ``config.yaml``)."""
    p = Path(path)
    if p.is_dir():
        p = p / "config.yaml"
    if not p.is_file():
        raise ValueError(f"{p}: no such file (give a config.yaml, .slp, .json, .mat or .toml)")
    suffix = p.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return read_dlc_config(p)
    if suffix in (".slp", ".json"):
        return read_sleap_skeleton(p)
    if suffix == ".mat":
        return read_dannce_skeleton(p)
    if suffix == ".toml":
        return read_anipose_constraints(p)
    raise ValueError(
        f"{p}: unknown keypoint definition (DeepLabCut config.yaml, SLEAP .slp/.json, "
        "DANNCE/Label3D .mat or anipose config.toml)"
    )


def _clean_edges(
    keypoints: list[str], pairs, source: str, notes: list[str]
) -> list[tuple[str, str]]:
    """Edges by name: unknown names, self-loops and repeats dropped (said in ``notes``)."""
    known = set(keypoints)
    out: list[tuple[str, str]] = []
    seen: set[frozenset] = set()
    for pair in pairs:
        if len(pair) != 2:
            raise ValueError(f"{source}: an edge must be a pair of names, got {pair!r}")
        a, b = str(pair[0]), str(pair[1])
        if a not in known or b not in known:
            notes.append(f"edge {a}-{b} names a keypoint that is not the animal's; dropped")
        elif a == b:
            notes.append(f"edge {a}-{b} joins a keypoint to itself; dropped")
        elif frozenset((a, b)) in seen:
            notes.append(f"edge {a}-{b} repeated; kept once")
        else:
            seen.add(frozenset((a, b)))
            out.append((a, b))
    return out


def read_dlc_config(path: str | Path) -> KeypointGraph:
    """DeepLabCut ``config.yaml``: ``bodyparts`` (or ``multianimalbodyparts``) and
    ``skeleton``. Multi-animal ``uniquebodyparts`` (arena landmarks) are left out."""
    p = Path(path)
    doc = load_dlc_config(p, "bodyparts")
    notes: list[str] = []
    if doc.get("multianimalproject"):
        kps = [str(b) for b in doc.get("multianimalbodyparts") or []]
        unique = [str(b) for b in doc.get("uniquebodyparts") or []]
        if unique:
            notes.append(f"uniquebodyparts {unique} are not the animal's; left out")
    else:
        bps = doc.get("bodyparts")
        kps = [] if bps == "MULTI!" else [str(b) for b in bps or []]
    if not kps:
        raise ValueError(f"{p}: no body parts in this config.yaml")
    edges = _clean_edges(kps, doc.get("skeleton") or [], str(p), notes)
    return KeypointGraph(kps, edges, [], str(p), "deeplabcut", notes)


def _resolve_pyids(doc):
    """jsonpickle's references resolved: every ``py/object`` or ``py/reduce`` gets the next id
    (1-based, in document order, when it starts), ``{"py/id": k}`` refers to it."""
    table: list = []

    def walk(x):
        if isinstance(x, dict):
            if set(x) == {"py/id"}:
                k = int(x["py/id"])
                if not 1 <= k <= len(table):
                    raise ValueError(f"py/id {k} refers to nothing")
                return table[k - 1]
            new = "py/object" in x or "py/reduce" in x
            slot = len(table)
            if new:
                table.append(None)
            out = {key: walk(v) for key, v in x.items()}
            if new:
                table[slot] = out
            return out
        if isinstance(x, list):
            return [walk(v) for v in x]
        return x

    return walk(doc)


def _node_name(node, names: list[str] | None) -> str:
    """A SLEAP node: an index into ``metadata.nodes`` (.slp) or a pickled ``Node``."""
    if isinstance(node, int):
        if names is None or not 0 <= node < len(names):
            raise ValueError(f"node index {node} outside the file's nodes")
        return names[node]
    if isinstance(node, dict):
        state = node.get("py/state", node)
        if isinstance(state, dict) and "py/tuple" in state:
            return str(state["py/tuple"][0])
        if isinstance(state, dict) and "name" in state:
            return str(state["name"])
    raise ValueError(f"cannot read a SLEAP node from {node!r}")


def _edge_type(t) -> int:
    """SLEAP's ``EdgeType``: 1 body, 2 symmetry (a pickled enum ``py/reduce``)."""
    if isinstance(t, dict) and "py/reduce" in t:
        return int(t["py/reduce"][1]["py/tuple"][0])
    if isinstance(t, int):
        return t
    raise ValueError(f"cannot read a SLEAP edge type from {t!r}")


def _sleap_graph(skel: dict, names: list[str] | None, source: str) -> KeypointGraph:
    skel = _resolve_pyids(skel)
    graph = skel.get("nx_graph", skel)
    nodes = [_node_name(n["id"], names) for n in graph.get("nodes", [])]
    if not nodes:
        raise ValueError(f"{source}: the SLEAP skeleton has no nodes")
    body, sym = [], []
    for link in graph.get("links", []):
        a, b = _node_name(link["source"], names), _node_name(link["target"], names)
        kind = _edge_type(link.get("type", 1))
        (sym if kind == 2 else body).append((a, b))
    notes: list[str] = []
    edges = _clean_edges(nodes, body, source, notes)
    pairs: list[tuple[str, str]] = []
    seen: set[frozenset] = set()
    for a, b in sym:  # SLEAP stores each symmetry both ways
        if frozenset((a, b)) not in seen and a != b:
            seen.add(frozenset((a, b)))
            pairs.append((a, b))
    return KeypointGraph(nodes, edges, pairs, source, "sleap", notes)


def read_sleap_skeleton(path: str | Path) -> KeypointGraph:
    """The skeleton of a SLEAP ``.slp`` (``metadata`` attribute ``json``, nodes stored as
    indices into its ``nodes``) or of a SLEAP skeleton ``.json`` (jsonpickle of the graph)."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: invalid JSON: {exc}") from None
        if isinstance(doc, list):  # a list of skeletons
            if len(doc) != 1:
                raise ValueError(f"{p}: {len(doc)} skeletons; give a file with one")
            doc = doc[0]
        if not isinstance(doc, dict) or "links" not in doc.get("nx_graph", doc):
            raise ValueError(f"{p}: not a SLEAP skeleton .json (no graph 'links')")
        return _sleap_graph(doc, None, str(p))
    import h5py

    try:
        f = h5py.File(p, "r")
    except OSError:
        raise ValueError(f"{p}: not an HDF5 file (damaged or not a SLEAP .slp)") from None
    with f:
        raw = f["metadata"].attrs.get("json") if "metadata" in f else None
    if raw is None:
        raise ValueError(f"{p}: not a SLEAP .slp (no metadata json)")
    meta = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    skeletons = meta.get("skeletons") or []
    if len(skeletons) != 1:
        raise ValueError(f"{p}: {len(skeletons)} skeletons; acm-rs reads SLEAP files with one")
    names = [str(n["name"]) for n in meta.get("nodes", [])]
    return _sleap_graph(skeletons[0], names, str(p))


def _mat_strings(x) -> list[str]:
    """A MATLAB cell array of strings as read by scipy (nested object arrays)."""
    out = []
    for item in np.asarray(x, dtype=object).ravel():
        while isinstance(item, np.ndarray) and item.dtype == object and item.size == 1:
            item = item.ravel()[0]
        if isinstance(item, np.ndarray):
            item = "".join(str(c) for c in item.ravel())
        out.append(str(item))
    return out


def read_dannce_skeleton(path: str | Path) -> KeypointGraph:
    """DANNCE / Label3D skeleton ``.mat``: ``joint_names`` (cell of strings) and
    ``joints_idx`` (n x 2, 1-based as MATLAB indexes)."""
    p = Path(path)
    try:
        import scipy.io

        d = scipy.io.loadmat(p)
        names = _mat_strings(d["joint_names"]) if "joint_names" in d else None
        idx = np.asarray(d["joints_idx"]) if "joints_idx" in d else None
    except NotImplementedError:  # MATLAB v7.3 = HDF5
        names, idx = _read_mat73(p)
    except ValueError as exc:
        raise ValueError(f"{p}: not a MATLAB file scipy can read ({exc})") from None
    if names is None or idx is None:
        raise ValueError(f"{p}: not a DANNCE/Label3D skeleton (needs joint_names, joints_idx)")
    idx = np.asarray(idx, dtype=np.int64).reshape(-1, 2)
    if idx.size and (idx.min() < 1 or idx.max() > len(names)):
        raise ValueError(
            f"{p}: joints_idx holds {idx.min()}..{idx.max()} for {len(names)} joint_names "
            "(1-based indices expected, as MATLAB writes them)"
        )
    notes: list[str] = []
    edges = _clean_edges(names, [(names[a - 1], names[b - 1]) for a, b in idx], str(p), notes)
    return KeypointGraph(names, edges, [], str(p), "dannce", notes)


def _read_mat73(p: Path) -> tuple[list[str] | None, np.ndarray | None]:
    import h5py

    with h5py.File(p, "r") as f:
        names = None
        if "joint_names" in f:
            refs = np.asarray(f["joint_names"]).ravel()
            names = ["".join(chr(int(c)) for c in np.asarray(f[r]).ravel()) for r in refs]
        # MATLAB stores column-major: an n x 2 array reads as 2 x n
        idx = np.asarray(f["joints_idx"]).T if "joints_idx" in f else None
    return names, idx


def read_anipose_constraints(path: str | Path) -> KeypointGraph:
    """anipose ``config.toml``: ``[triangulation] constraints``; the keypoints are the names
    the constraints use (``constraints_weak`` are soft and left out, as noted)."""
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p}: invalid TOML: {exc}") from None
    tri = doc.get("triangulation") or {}
    pairs = tri.get("constraints") or []
    if not pairs:
        raise ValueError(f"{p}: no [triangulation] constraints in this anipose config")
    kps: list[str] = []
    for pair in pairs:
        for n in pair:
            if str(n) not in kps:
                kps.append(str(n))
    notes = []
    if tri.get("constraints_weak"):
        notes.append(f"{len(tri['constraints_weak'])} constraints_weak (soft) left out")
    return KeypointGraph(kps, _clean_edges(kps, pairs, str(p), notes), [], str(p), "anipose", notes)


# -- left/right -------------------------------------------------------------------------------
_WORD = re.compile(r"(?i)left|right")
# a single L/R: at the start or after a separator or a lowercase letter (camelCase), and
# before the end, a separator, a digit or an uppercase letter (EarL, L-ear, wingL1, LF-paw)
_LETTER = re.compile(r"(?:(?<=^)|(?<=[_\-\s.()])|(?<=[a-z]))([LR])(?=$|[_\-\s.()0-9A-Z])")
_LETTER_LOWER = re.compile(r"(?:(?<=^)|(?<=[_\-\s.()]))([lr])(?=$|[_\-\s.()0-9])")


def _swap(m: re.Match) -> str:
    s = m.group(0)
    other = {"left": "right", "right": "left", "l": "r", "r": "l"}[s.lower()]
    if s.isupper():
        return other.upper()
    return other.capitalize() if s[0].isupper() else other


def symmetry_from_names(names: Sequence[str]) -> list[tuple[str, str]]:
    """Left/right pairs by name: two keypoints whose names differ only in a side word
    (``left``/``right``, any case, anywhere) or a single ``L``/``R`` letter standing as a
    token (``Ear_L``, ``L-ear``, ``EarL``, ``wingL1``, ``LF-paw``). Each name is in at most one
    pair; ``(left, right)`` order."""
    known = list(names)
    out: list[tuple[str, str]] = []
    used: set[str] = set()
    for name in known:
        if name in used:
            continue
        for pattern in (_WORD, _LETTER, _LETTER_LOWER):
            hit = None
            for m in pattern.finditer(name):
                other = name[: m.start()] + _swap(m) + name[m.end() :]
                if other != name and other in known and other not in used:
                    hit = (m.group(0).lower().startswith("l"), other)
                    break
            if hit:
                is_left, other = hit
                out.append((name, other) if is_left else (other, name))
                used.update((name, other))
                break
    return out


# -- the tree ---------------------------------------------------------------------------------
@dataclass
class KeypointTree:
    """A rooted tree over the keypoints.

    Attributes
    ----------
    names : list of str
        Keypoints, root first, breadth-first (children in the definition's order).
    parents : list of int
        Parent index in ``names`` (-1 for the root).
    root : str
    dropped : list of (str, str)
        Lab edges not in the tree (they closed a cycle).
    added : list of (str, str)
        Pairs added to join pieces of the lab's graph.
    rule : str
        ``"rigidity"`` (maximum spanning tree by length constancy) or ``"bfs"``.
    cv : dict
        Coefficient of variation of the labelled length of each tree edge ``(parent, child)``.
    """

    names: list[str]
    parents: list[int]
    root: str
    dropped: list[tuple[str, str]]
    added: list[tuple[str, str]]
    rule: str
    cv: dict = field(default_factory=dict)

    def summary(self) -> str:
        """One line: root, dropped and added edges."""
        line = f"tree of {len(self.names)} keypoints rooted at {self.root!r} ({self.rule})"
        if self.dropped:
            line += "; dropped edges " + ", ".join(f"{a}-{b}" for a, b in self.dropped)
        if self.added:
            line += "; added edges " + ", ".join(f"{a}-{b}" for a, b in self.added)
        return line


def _edge_cv(points: np.ndarray, i: int, j: int) -> float:
    """Coefficient of variation of the distance between keypoints i, j over the frames where
    both are triangulated (inf with fewer than 2 such frames)."""
    d = np.linalg.norm(points[:, i] - points[:, j], axis=-1)
    d = d[np.isfinite(d)]
    if d.size < 2 or d.mean() <= 0:
        return float("inf")
    return float(d.std() / d.mean())


class _Union:
    def __init__(self, n: int) -> None:
        self.p = list(range(n))

    def find(self, a: int) -> int:
        while self.p[a] != a:
            self.p[a] = self.p[self.p[a]]
            a = self.p[a]
        return a

    def join(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.p[rb] = ra
        return True


def _eccentricity(adj: list[list[int]], start: int) -> int:
    dist = {start: 0}
    queue = [start]
    for a in queue:
        for b in adj[a]:
            if b not in dist:
                dist[b] = dist[a] + 1
                queue.append(b)
    return max(dist.values()) if len(dist) == len(adj) else 10**9


def _centre(names: list[str], adj: list[list[int]]) -> int:
    """Least eccentricity; ties by name order."""
    return min(range(len(names)), key=lambda k: (_eccentricity(adj, k), names[k]))


def _pieces(names: list[str], adj: list[list[int]]) -> list[list[str]]:
    seen: set[int] = set()
    out = []
    for s in range(len(names)):
        if s in seen:
            continue
        comp, queue = [], [s]
        seen.add(s)
        for a in queue:
            comp.append(names[a])
            for b in adj[a]:
                if b not in seen:
                    seen.add(b)
                    queue.append(b)
        out.append(comp)
    return out


def spanning_tree(
    keypoints: Sequence[str],
    edges: Sequence[tuple[str, str]],
    points: np.ndarray | None = None,
    root: str | None = None,
) -> KeypointTree:
    """A rooted spanning tree of the lab's graph.

    Parameters
    ----------
    keypoints : sequence of str, length K
    edges : sequence of (str, str)
    points : array_like, shape (F, K, 3), optional
        Triangulated keypoints of the labelled frames (NaN where missing). With them the tree
        keeps the most rigid edges (Kruskal on the coefficient of variation of each edge's
        length; ties in the lab's order) and joins pieces of the graph by the most rigid
        pairs between them; without them it is the breadth-first tree from the root.
    root : str, optional
        Root keypoint; default the tree's centre (least eccentricity, ties by name).

    Raises
    ------
    ValueError
        An unknown root, or a graph in pieces without ``points`` to join them.
    """
    names = list(keypoints)
    k = len(names)
    index = {n: i for i, n in enumerate(names)}
    if root is not None and root not in index:
        raise ValueError(f"root {root!r} is not a keypoint; keypoints: {names}")
    pairs = [(index[a], index[b]) for a, b in edges]
    full_adj: list[list[int]] = [[] for _ in range(k)]
    for a, b in pairs:
        full_adj[a].append(b)
        full_adj[b].append(a)
    if points is None:
        pieces = _pieces(names, full_adj)
        if len(pieces) > 1:
            raise ValueError(
                f"the keypoint graph is in {len(pieces)} pieces ({'; '.join(map(str, pieces))}): "
                "give labelled frames to join them, or add edges in the lab's tool"
            )
        start = index[root] if root is not None else _centre(names, full_adj)
        parent = {start: -1}
        queue = [start]
        for a in queue:
            for b in sorted(full_adj[a]):
                if b not in parent:
                    parent[b] = a
                    queue.append(b)
        tree = [(parent[b], b) for b in parent if parent[b] >= 0]
        rule, cvs, added = "bfs", {}, []
    else:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 3 or pts.shape[1:] != (k, 3):
            raise ValueError(f"points must have shape (F, {k}, 3), got {pts.shape}")
        cv = {p: _edge_cv(pts, *p) for p in pairs}
        uf = _Union(k)
        order = sorted(range(len(pairs)), key=lambda e: (cv[pairs[e]], e))
        tree = [pairs[e] for e in order if uf.join(*pairs[e])]
        added = []
        if len(tree) < k - 1:  # pieces: join by the most rigid pairs between them
            extra = [(_edge_cv(pts, a, b), a, b) for a in range(k) for b in range(a + 1, k)
                     if uf.find(a) != uf.find(b)]  # fmt: skip
            for c, a, b in sorted(extra):
                if np.isfinite(c) and uf.join(a, b):
                    tree.append((a, b))
                    added.append((names[a], names[b]))
                    cv[(a, b)] = c
        if len(tree) < k - 1:
            adj = [[] for _ in range(k)]
            for a, b in tree:
                adj[a].append(b)
                adj[b].append(a)
            raise ValueError(
                "the keypoints cannot be joined into one tree: pieces "
                f"{'; '.join(map(str, _pieces(names, adj)))} share no frame where both are "
                "triangulated (label them together in at least 2 frames)"
            )
        rule, cvs = "rigidity", cv
    adj = [[] for _ in range(k)]
    for a, b in tree:
        adj[a].append(b)
        adj[b].append(a)
    start = index[root] if root is not None else _centre(names, adj)
    parent = {start: -1}
    queue = [start]
    for a in queue:
        for b in sorted(adj[a]):
            if b not in parent:
                parent[b] = a
                queue.append(b)
    kept = {frozenset(p) for p in tree}
    dropped = [(names[a], names[b]) for a, b in pairs if frozenset((a, b)) not in kept]
    pos = {old: new for new, old in enumerate(queue)}
    out_cv = {}
    for (a, b), c in cvs.items() if rule == "rigidity" else []:
        if frozenset((a, b)) in kept:
            pa, ch = (a, b) if parent.get(b) == a else (b, a)
            out_cv[(names[pa], names[ch])] = c
    return KeypointTree(
        names=[names[i] for i in queue],
        parents=[-1 if parent[i] < 0 else pos[parent[i]] for i in queue],
        root=names[start],
        dropped=dropped,
        added=added,
        rule=rule,
        cv=out_cv,
    )


# -- geometry ---------------------------------------------------------------------------------
def _kabsch(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum |R x + t - y|^2 (proper rotation)."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    u, _, vt = np.linalg.svd((x - mx).T @ (y - my))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, my - rot @ mx


def rest_shape(points: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, int]:
    """Median shape of triangulated frames after rigid (Kabsch) alignment.

    Parameters
    ----------
    points : array_like, shape (F, K, 3)
        NaN where a keypoint is not triangulated.

    Returns
    -------
    shape : numpy.ndarray, shape (K, 3)
        NaN for keypoints never triangulated.
    n_aligned : int
        Frames that shared >= 3 keypoints with the reference and were used.
    """
    pts = np.asarray(points, dtype=np.float64)
    ok = np.isfinite(pts).all(axis=-1)
    if not ok.any():
        return np.full(pts.shape[1:], np.nan), 0
    ref = pts[int(np.argmax(ok.sum(axis=1)))].copy()
    used = 0
    for _ in range(iterations):
        aligned = []
        for f in range(pts.shape[0]):
            both = ok[f] & np.isfinite(ref).all(axis=-1)
            if both.sum() < 3:
                continue
            rot, t = _kabsch(pts[f, both], ref[both])
            aligned.append(pts[f] @ rot.T + t)
        used = len(aligned)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN keypoints stay NaN
            ref = np.nanmedian(np.stack(aligned), axis=0)
    return ref, used


def _body_frame(shape: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Rows = body axes in the data's frame: x the animal's right (mean right - left of the
    pairs, else the second principal axis), z the long (first principal) axis orthogonal to
    x, y = z x x (ACM's x right, y dorsal, z caudal; signs from the data)."""
    c = shape - shape.mean(axis=0)
    x = None
    if pairs:
        v = np.mean([shape[r] - shape[lf] for lf, r in pairs], axis=0)
        if np.linalg.norm(v) > 1e-9 * max(np.abs(c).max(), 1e-300):
            x = v / np.linalg.norm(v)
    if x is None:
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        x = vt[1] if vt.shape[0] > 1 else np.array([1.0, 0.0, 0.0])
    cp = c - np.outer(c @ x, x)
    _, _, vt = np.linalg.svd(cp, full_matrices=False)
    z = vt[0] - (vt[0] @ x) * x
    if np.linalg.norm(z) < 1e-9:
        z = np.cross(x, [0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.cross(x, [0.0, 1.0, 0.0])
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _swing(dbar: np.ndarray, u: np.ndarray, c: int) -> np.ndarray:
    """Rodrigues vectors (..., 3) turning unit ``dbar`` onto unit ``u`` (..., 3) whose component
    ``c`` is zero: the axis n is orthogonal to e_c and equidistant from dbar and u, so
    n = (dbar - u) x e_c; the angle is that between their projections orthogonal to n."""
    e = np.zeros(3)
    e[c] = 1.0
    dbar = np.broadcast_to(dbar, u.shape)
    n = np.cross(dbar - u, e)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    # dbar - u along e_c (or dbar == u): the plain shortest turn, then without its c part
    fallback = np.cross(dbar, u)
    fallback[..., c] = 0.0
    n = np.where(norm > 1e-12, n / np.where(norm > 0, norm, 1.0), fallback)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(nn > 1e-12, n / np.where(nn > 0, nn, 1.0), 0.0)
    a = dbar - np.sum(dbar * n, axis=-1, keepdims=True) * n
    b = u - np.sum(u * n, axis=-1, keepdims=True) * n
    theta = np.arctan2(np.sum(np.cross(a, b) * n, axis=-1), np.sum(a * b, axis=-1))
    return theta[..., None] * n


def poses_from_points(
    skeleton: Skeleton, points: np.ndarray, fixed_axis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses that put every joint on its triangulated keypoint's direction (exact, root first).

    Parameters
    ----------
    skeleton : Skeleton
        Joints = keypoints (marker k at joint k).
    points : array_like, shape (F, J, 3)
        Triangulated joints in joint order, NaN where missing.
    fixed_axis : array_like of int, shape (n_bones,)
        Per bone the Rodrigues component held at 0.

    Returns
    -------
    t : numpy.ndarray, shape (F, 3)
    r : numpy.ndarray, shape (F, n_bones, 3)
        NaN where the bone's end or an ancestor's is missing.
    """
    pts = np.asarray(points, dtype=np.float64)
    rest_j, _ = skeleton.rest_pose()
    n_f = pts.shape[0]
    bones = skeleton.bones
    bone_of_end = {int(e): b for b, e in enumerate(bones[:, 1])}
    acc = {int(np.flatnonzero(skeleton.parents == -1)[0]): np.broadcast_to(np.eye(3), (n_f, 3, 3))}
    r = np.full((n_f, skeleton.n_bones, 3), np.nan)
    for j in range(skeleton.n_joints):  # parents come first (breadth-first joint order)
        p = int(skeleton.parents[j])
        if p < 0:
            continue
        b = bone_of_end[j]
        dbar = rest_j[j] - rest_j[p]
        dbar /= np.linalg.norm(dbar)
        d = pts[:, j] - pts[:, p]
        with np.errstate(invalid="ignore", divide="ignore"):
            d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        u = np.einsum("fji,fj->fi", acc[p], d)  # A_parent^T d
        r[:, b] = _swing(dbar, u, int(fixed_axis[b]))
        acc[j] = acc[p] @ rodrigues(np.nan_to_num(r[:, b]))
        acc[j] = np.where(np.isfinite(r[:, b, :1])[..., None], acc[j], np.nan)
    root = int(np.flatnonzero(skeleton.parents == -1)[0])
    return pts[:, root].copy(), r


# -- the skeleton -----------------------------------------------------------------------------
@dataclass
class LabSkeleton:
    """Result of :func:`skeleton_from_labels`.

    Attributes
    ----------
    skeleton : Skeleton
    graph : KeypointGraph
    tree : KeypointTree
    lengths : dict
        Median labelled length of each bone (by end keypoint, world units).
    n_frames : int
        Labelled frames used for the rest pose.
    notes : list of str
        What was dropped, added or assumed.
    """

    skeleton: Skeleton
    graph: KeypointGraph
    tree: KeypointTree
    lengths: dict
    n_frames: int
    notes: list[str]

    def summary(self) -> str:
        """A few lines for the log."""
        sk = self.skeleton
        lines = [
            f"{sk.name}: {sk.n_joints} keypoints, {sk.n_bones} bones from {self.graph.tool} "
            f"{Path(self.graph.source).name}; rest pose from {self.n_frames} labelled frames",
            "  " + self.tree.summary(),
            f"  left/right pairs: {len(sk.symmetry['joints'])}"
            + (
                " (" + ", ".join(f"{a}/{b}" for a, b in sk.symmetry["joints"]) + ")"
                if sk.symmetry["joints"] else ""
            ),
            f"  free pose entries: {int((~sk.fixed_pose_mask).sum())} "
            f"(one twist component per bone fixed at 0)",
        ]  # fmt: skip
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def _labels_array(labels, bodyparts: Sequence[str] | None) -> tuple[np.ndarray, list[str]]:
    if hasattr(labels, "points") and hasattr(labels, "bodyparts"):
        return np.asarray(labels.points, dtype=np.float64), list(labels.bodyparts)
    arr = np.asarray(labels, dtype=np.float64)
    if bodyparts is None:
        raise ValueError("labels given as an array need bodyparts= (the column names)")
    return arr, list(bodyparts)


def skeleton_from_labels(
    graph: KeypointGraph | str | Path,
    rig: CameraRig,
    labels,
    *,
    bodyparts: Sequence[str] | None = None,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.0,
    root: str | None = None,
    joint_limits: bool = True,
    limit_margin_deg: float = LIMIT_MARGIN_DEG,
    name: str | None = None,
) -> LabSkeleton:
    """Build a skeleton from a lab's keypoint definition and its labelled frames.

    Parameters
    ----------
    graph : KeypointGraph or path
        The lab's definition (:func:`read_keypoint_graph` reads a path).
    rig : CameraRig
        Calibration of the labelled cameras; the skeleton takes its units.
    labels : LabelSet or array_like, shape (n_cams, F, n_columns, 2)
        Labelled pixels, NaN where not labelled; columns named by ``labels.bodyparts`` or
        ``bodyparts``.
    likelihood : array_like, shape (n_cams, F, n_columns), optional
        Scores of predicted labels (default ``labels.likelihood``); below ``pcutoff`` unused.
    root : str, optional
        Root keypoint (default the tree's centre).
    joint_limits : bool
        Limits from the labelled poses (range + ``limit_margin_deg`` each side) or none.
    name : str, optional
        Model name (default the definition file's stem).

    Returns
    -------
    LabSkeleton

    Raises
    ------
    ValueError
        A keypoint never labelled in 2 cameras of one frame, labels for another number of
        cameras, no frame with 3 triangulated keypoints.
    """
    g = graph if isinstance(graph, KeypointGraph) else read_keypoint_graph(graph)
    notes = list(g.notes)
    lab, cols = _labels_array(labels, bodyparts)
    if likelihood is None and hasattr(labels, "likelihood"):
        likelihood = labels.likelihood
    if lab.ndim != 4 or lab.shape[-1] != 2 or lab.shape[0] != len(rig) or lab.shape[2] != len(cols):
        raise ValueError(
            f"labels must have shape ({len(rig)} cameras, frames, {len(cols)} columns, 2), "
            f"got {lab.shape}"
        )
    if likelihood is not None and pcutoff > 0:
        lab = np.where((np.asarray(likelihood) >= pcutoff)[..., None], lab, np.nan)
    missing = [k for k in g.keypoints if k not in cols]
    if missing:
        raise ValueError(
            f"{g.source}: keypoints {missing} have no labels (label columns: {cols}); "
            "label them or remove them from the definition"
        )
    extra = [c for c in cols if c not in g.keypoints]
    if extra:
        notes.append(f"label columns {extra} are not keypoints of {Path(g.source).name}; unused")
    lab = lab[:, :, [cols.index(k) for k in g.keypoints]]
    pts = triangulate(rig, lab)  # (F, K, 3)
    never = [k for i, k in enumerate(g.keypoints) if not np.isfinite(pts[:, i]).all(-1).any()]
    if never:
        raise ValueError(
            f"keypoints {never} are never labelled in 2 cameras of one frame: no 3D position; "
            "label them in at least 2 cameras"
        )
    tree = spanning_tree(g.keypoints, g.edges, pts, root)
    if tree.added:
        warnings.warn(
            f"{g.source}: the keypoint graph is in pieces; joined by the most rigid pairs "
            + ", ".join(f"{a}-{b}" for a, b in tree.added),
            stacklevel=2,
        )
    order = [g.keypoints.index(n) for n in tree.names]
    pts = pts[:, order]
    shape, n_used = rest_shape(pts)
    if n_used == 0:
        raise ValueError("no labelled frame has 3 keypoints triangulated: cannot build a rest pose")
    lost = [n for n, ok in zip(tree.names, np.isfinite(shape).all(axis=1), strict=True) if not ok]
    if lost:
        raise ValueError(
            f"keypoints {lost} are triangulated only in frames that share < 3 keypoints with "
            "the others: no rest position; label them in frames with more keypoints"
        )
    # each bone at its median labelled length, along the median shape's direction
    lengths = {}
    rest = np.zeros_like(shape)
    for j, p in enumerate(tree.parents):
        if p < 0:
            continue
        d = np.linalg.norm(pts[:, j] - pts[:, p], axis=-1)
        length = float(np.nanmedian(d))
        lengths[tree.names[j]] = length
        direction = shape[j] - shape[p]
        rest[j] = rest[p] + length * direction / np.linalg.norm(direction)
    names = tree.names
    sym = list(g.symmetry)
    seen = {n for pair in sym for n in pair}
    sym += [p for p in symmetry_from_names(names) if not seen & set(p)]
    sym = [(a, b) for a, b in sym if a in names and b in names]
    pair_idx = [(names.index(a), names.index(b)) for a, b in sym]
    axes = _body_frame(rest, pair_idx)
    rest = (rest - rest[0]) @ axes.T  # root at the origin, body frame
    joint_sym = [(a, b) for a, b in sym if a != tree.root and b != tree.root]
    if len(joint_sym) < len(sym):
        notes.append(f"root {tree.root!r} is in a left/right pair; that pair is not a bone pair")
    k = len(names)
    base = Skeleton.from_rest_pose(
        names, tree.parents, rest, names, names, rest, up=(0.0, 1.0, 0.0),
        name=name or Path(g.source).stem, units=rig.units,
        symmetry={"joints": joint_sym, "markers": sym},
        marker_bounds=np.zeros((k, 3, 2)),
    )  # fmt: skip
    dirs = np.array([rest[e] - rest[s] for s, e in base.bones])
    fixed_axis = np.argmax(np.abs(dirs), axis=1)
    limits = np.tile(np.array([-np.inf, np.inf]), (base.n_bones, 3, 1))
    limits[np.arange(base.n_bones), fixed_axis] = 0.0
    if joint_limits:
        _, r = poses_from_points(base, pts, fixed_axis)
        margin = np.radians(float(limit_margin_deg))
        root_bones = set(base.root_bones.tolist())
        for b in range(base.n_bones):
            seen_r = r[:, b][np.isfinite(r[:, b]).all(axis=-1)]
            if b in root_bones or seen_r.shape[0] == 0:
                continue
            for ax in range(3):
                if ax != fixed_axis[b]:
                    lo = max(seen_r[:, ax].min() - margin, -np.pi)
                    hi = min(seen_r[:, ax].max() + margin, np.pi)
                    limits[b, ax] = (lo, hi)
        notes.append(
            f"joint limits: labelled range +- {limit_margin_deg:g} deg per free component "
            f"({n_used} frames; root bones unbounded)"
        )
    sk = Skeleton.from_rest_pose(
        names, tree.parents, rest, names, names, rest, up=(0.0, 1.0, 0.0),
        name=name or Path(g.source).stem, units=rig.units,
        symmetry={"joints": joint_sym, "markers": sym},
        marker_bounds=np.zeros((k, 3, 2)), joint_limits=limits,
    )  # fmt: skip
    return LabSkeleton(sk, g, tree, lengths, n_used, notes)
