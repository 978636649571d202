"""Sequence windows over one or many store collections, in the policies' batch format.

Windows follow robomimic's SequenceDataset with ``pad_seq_length=True``: a window may start at any
step of an episode and runs past its end by repeating the last step (``pad_mask`` marks the real
steps); with ``pad=False`` only windows that fit inside the episode are used. Values are RAW
(images uint8, depth in metres, lowdim and actions unnormalised); ``stats()`` gives the store's
statistics for the policy's normaliser. Arrays are read lazily, chunk by chunk, through a small
per-process cache, so memory does not grow with the store; the index holds a few numbers per
episode, not per window.
"""

from __future__ import annotations

import json
import os
import sys
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterable

import numcodecs.blosc as blosc
import numpy as np
import torch
import zarr
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate, get_worker_info
from zarr.codecs import BloscCodec, BytesCodec
from zarr.codecs.bytes import Endian
from zarr.storage import LocalStore

from nostra.data.errors import CollectionError
from nostra.data.store import Store
from nostra.modality import Modality, kind_of_key


class ChunkCache:
    """Least-recently-used decoded chunks (along time), bounded in bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes, self.bytes, self.items = max_bytes, 0, OrderedDict()
        self.readers: dict = {}

    def rows(self, key, arr, a: int, b: int) -> np.ndarray:
        """Rows a..b-1 of ``arr`` (``key`` names it in the cache)."""
        c = arr.chunks[0]
        parts = []
        for ci in range(a // c, (b - 1) // c + 1):
            chunk = self._chunk(key, arr, ci)
            parts.append(chunk[max(a, ci * c) - ci * c:min(b, (ci + 1) * c) - ci * c])
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _chunk(self, key, arr, ci: int) -> np.ndarray:
        if (key, ci) in self.items:
            self.items.move_to_end((key, ci))
            return self.items[(key, ci)]
        if key not in self.readers:
            self.readers[key] = chunk_reader(arr)
        x = self.readers[key](ci)
        self.items[(key, ci)] = x
        self.bytes += x.nbytes
        while self.bytes > self.max_bytes and len(self.items) > 1:
            self.bytes -= self.items.popitem(last=False)[1].nbytes
        return x


def chunk_reader(arr: zarr.Array) -> Callable[[int], np.ndarray]:
    """A function reading chunk ``i`` along time. The store's own arrays (local files, bytes +
    Blosc codecs, as the zarr v3 spec lays them out) are read straight from their chunk files:
    about 3x faster than zarr's async path for these small reads. Anything else goes through zarr."""
    c, m, store = arr.chunks[0], arr.metadata, arr.store_path.store
    plain = (m.zarr_format == 3 and isinstance(store, LocalStore) and sys.byteorder == "little"
             and len(m.codecs) == 2 and isinstance(m.codecs[0], BytesCodec) and isinstance(m.codecs[1], BloscCodec)
             and m.codecs[0].endian in (None, Endian.little))
    if not plain:
        return lambda i: arr[i * c:(i + 1) * c]
    root, rest = Path(store.root) / arr.store_path.path, (0,) * (arr.ndim - 1)
    shape, dtype, fill = tuple(m.chunk_grid.chunk_shape), arr.dtype, m.fill_value

    def read(i: int) -> np.ndarray:
        try:
            raw = (root / m.encode_chunk_key((i, *rest))).read_bytes()
        except FileNotFoundError:  # zarr does not write chunks that are all fill value
            return np.full(shape, fill, dtype)
        out = np.empty(shape, dtype)
        blosc.decompress(raw, out)
        return out

    return read


def _empty(shape, dtype) -> torch.Tensor:
    """A batch buffer; in a loader worker it is made in shared memory, so handing the batch to
    the training process needs no copy (batches of images are tens of MB)."""
    t = torch.from_numpy(np.empty(shape, dtype))
    return t.share_memory_() if get_worker_info() is not None else t


def _as_pairs(episodes) -> list[tuple[str, int]]:
    if hasattr(episodes, "columns"):  # a manifest DataFrame
        return [(str(c), int(e)) for c, e in zip(episodes["collection"], episodes["episode"])]
    return [(str(c), int(e)) for c, e in episodes]


class SequenceDataset(Dataset):
    def __init__(self, store: Store | str | os.PathLike, collections: Iterable[str] | None = None,
                 keys: Iterable[str] = (), seq_len: int = 16, pad: bool = True,
                 episodes: Iterable[tuple[str, int]] | None = None, cache_mb: float = 64):
        self.store = store if isinstance(store, Store) else Store(store)
        pairs = _as_pairs(episodes) if episodes is not None else None
        if collections is None:
            collections = list(dict.fromkeys(c for c, _ in pairs)) if pairs is not None else self.store.collections()
        self.collections = list(collections)
        if not self.collections:
            raise CollectionError(f"no collections to read from store {self.store.path}; it has "
                                  f"{self.store.collections() or 'none'}")
        self.keys = [k.name if isinstance(k, Modality) else str(k) for k in keys]
        self.seq_len, self.pad = int(seq_len), bool(pad)
        if self.seq_len < 1:
            raise ValueError(f"seq_len must be >= 1, got {seq_len}")
        self.shapes = self._check_keys()
        self._index(pairs)
        self.cache_bytes = int(cache_mb * 2 ** 20)
        self._pid, self._arrays, self._cache = None, {}, None

    def _check_keys(self) -> dict[str, tuple]:
        shapes: dict[str, tuple] = {}
        self.dtypes: dict[str, np.dtype] = {}
        for c in self.collections:
            have = self.store.keys(c)
            missing = [k for k in [*self.keys, "actions"] if k not in have]
            if missing:
                raise CollectionError(f"collection {c!r} has no key {missing[0]!r} (missing {missing} of the "
                                      f"requested keys {self.keys}); it has {have}")
            for k in [*self.keys, "actions"]:
                arr = self.store.array(c, k)
                shape = tuple(arr.shape[1:])
                # batches are float32 for the models; the store keeps the source's float64
                self.dtypes.setdefault(k, np.dtype(np.float32) if arr.dtype == np.float64 else arr.dtype)
                if shapes.setdefault(k, shape) != shape:
                    raise CollectionError(f"key {k!r} has per-step shape {shape} in collection {c!r} but "
                                          f"{shapes[k]} in {self.collections[0]!r}")
        return shapes

    def _index(self, pairs) -> None:
        stray = sorted({c for c, _ in pairs or []} - set(self.collections))
        if stray:
            raise CollectionError(f"episodes given from {stray}, which are not among the collections read: "
                                  f"{self.collections}")
        coll, index, start, length = [], [], [], []
        for ci, c in enumerate(self.collections):
            ends = self.store.episode_ends(c)
            eps = range(len(ends)) if pairs is None else sorted({e for cc, e in pairs if cc == c})
            for e in eps:
                if not 0 <= e < len(ends):
                    raise CollectionError(f"collection {c!r} has episodes 0..{len(ends) - 1}, not {e}")
                coll.append(ci)
                index.append(e)
                start.append(ends[e - 1] if e else 0)
                length.append(ends[e] - start[-1])
        self.ep_coll = np.asarray(coll, np.int32)
        self.ep_start = np.asarray(start, np.int64)
        self.ep_len = np.asarray(length, np.int64)
        self.ep_index = np.asarray(index, np.int64)
        n_win = self.ep_len if self.pad else np.maximum(0, self.ep_len - self.seq_len + 1)
        self.cum = np.cumsum(n_win)
        bounds = np.searchsorted(self.ep_coll, np.arange(len(self.collections) + 1))  # episodes grouped by collection
        first = np.concatenate([[0], self.cum])
        self.ranges = {c: (int(first[bounds[i]]), int(first[bounds[i + 1]])) for i, c in enumerate(self.collections)}

    def __len__(self) -> int:
        return int(self.cum[-1]) if len(self.cum) else 0

    def _find(self, i: int) -> tuple[int, int]:
        """Window ``i`` -> (row in the episode index, first step within the episode)."""
        if not 0 <= i < len(self):
            raise IndexError(f"window {i} out of range 0..{len(self) - 1}")
        e = int(np.searchsorted(self.cum, i, side="right"))
        return e, i - (int(self.cum[e - 1]) if e else 0)

    def locate(self, i: int) -> tuple[str, int, int]:
        """Window ``i`` -> (collection, episode index, first step within the episode)."""
        e, t0 = self._find(int(i))
        return self.collections[self.ep_coll[e]], int(self.ep_index[e]), t0

    def stats(self) -> dict[str, dict]:
        keys = [k for k in self.keys if kind_of_key(k) == "lowdim"] + ["actions"]
        return self.store.stats(self.collections, keys)

    def modalities(self) -> list[Modality]:
        return [Modality(k, kind_of_key(k), self.shapes[k]) for k in self.keys]

    @property
    def action_dim(self) -> int:
        return int(self.shapes["actions"][0])

    def _array(self, c: str, k: str):
        if self._pid != os.getpid():  # opened lazily in each worker process
            self._pid, self._arrays, self._cache = os.getpid(), {}, ChunkCache(self.cache_bytes)
        if (c, k) not in self._arrays:
            self._arrays[(c, k)] = self.store.array(c, k)
        return self._arrays[(c, k)]

    def __getitem__(self, i: int) -> dict:
        b = self.__getitems__([i])
        return {"obs": {k: v[0] for k, v in b["obs"].items()}, "actions": b["actions"][0], "pad_mask": b["pad_mask"][0]}

    def __getitems__(self, indices) -> dict:
        """A whole batch at once (DataLoader calls this): windows are copied straight into the
        batch arrays, padded past an episode's end by repeating its last step."""
        B, T = len(indices), self.seq_len
        t = {k: _empty((B, T, *self.shapes[k]), self.dtypes[k]) for k in [*self.keys, "actions"]}
        out = {k: v.numpy() for k, v in t.items()}
        mask = np.zeros((B, T), bool)
        for j, i in enumerate(indices):
            e, t0 = self._find(int(i))
            c, a = self.collections[self.ep_coll[e]], int(self.ep_start[e]) + t0
            real = min(T, int(self.ep_len[e]) - t0)
            mask[j, :real] = True
            for k, buf in out.items():
                arr = self._array(c, k)  # opens arrays and the cache in this process first
                buf[j, :real] = self._cache.rows((c, k), arr, a, a + real)
                buf[j, real:] = buf[j, real - 1]
        return {"obs": {k: t[k] for k in self.keys}, "actions": t["actions"], "pad_mask": torch.from_numpy(mask)}

    def __getstate__(self):
        state = dict(self.__dict__)
        state.update(_pid=None, _arrays={}, _cache=None)
        return state


def dist_world() -> tuple[int, int]:
    """(rank, world size) in torch.distributed's default process group; (0, 1) outside one."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def _epoch_seed(seed: int, epoch: int, resumed_at: int = 0) -> int:
    words = [int(seed) % 2 ** 63, int(epoch)] + ([int(resumed_at)] if resumed_at else [])
    return int(np.random.SeedSequence(words).generate_state(1, np.uint64)[0])


class ShardedSampler(Sampler[int]):
    """An index stream fixed by (seed, epoch) alone, sharded over the ranks of a distributed run:
    rank r of w yields the stream's elements r, r + w, r + 2w, ... So the w ranks' k-th batches
    together are exactly the k-th batch of one process drawing with w times the batch size, and
    each rank draws different windows. Rank and world size are read when iterating (from
    torch.distributed once its process group exists), so a loader built before the trainer starts
    its processes shards all the same; ``rank``/``world_size`` override them. The epoch advances
    with each pass, or is set by ``set_epoch`` (Lightning calls it at each epoch, also on resume).
    ``resumed_at``: the step a resumed run starts from. Lightning resumes mid-epoch with a new
    iterator over the loader; a stream seeded by it too does not replay the epoch's first windows."""

    def __init__(self, seed: int = 0, rank: int | None = None, world_size: int | None = None):
        self.seed, self.epoch, self.resumed_at = int(seed), 0, 0
        if (rank is None) != (world_size is None) or (world_size is not None and not 0 <= rank < world_size):
            raise ValueError(f"rank and world_size go together, with 0 <= rank < world_size; got {rank}, {world_size}")
        self.rank, self.world_size = rank, world_size

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def world(self) -> tuple[int, int]:
        return (self.rank, self.world_size) if self.rank is not None else dist_world()

    def _total(self, world: int) -> int:
        """Length of the whole stream the ranks share."""
        raise NotImplementedError

    def _stream(self, n: int, g: torch.Generator) -> torch.Tensor:
        raise NotImplementedError

    def __len__(self) -> int:
        return self._total(self.world()[1]) // self.world()[1]

    def __iter__(self):
        rank, world = self.world()
        g = torch.Generator().manual_seed(_epoch_seed(self.seed, self.epoch, self.resumed_at))
        self.epoch += 1
        return iter(self._stream(self._total(world), g)[rank::world].tolist())


class MixtureSampler(ShardedSampler):
    """Draws a collection by its weight, then a window uniformly within it; memory is per
    collection, not per window. Each rank draws ``num_samples`` per epoch."""

    def __init__(self, ranges: dict[str, tuple[int, int]], weights: dict[str, float], num_samples: int,
                 seed: int = 0, rank: int | None = None, world_size: int | None = None):
        super().__init__(seed, rank, world_size)
        unknown = set(weights) - set(ranges)
        if unknown:
            raise CollectionError(f"weights given for {sorted(unknown)}, which are not read; collections: {list(ranges)}")
        names = [c for c in ranges if ranges[c][1] > ranges[c][0] and weights.get(c, 0) > 0]
        if not names:
            raise ValueError(f"no collection with windows has a positive weight: weights {weights}, ranges {ranges}")
        if any(w < 0 for w in weights.values()):
            raise ValueError(f"mixture weights must be >= 0, got {weights}")
        self.lo = torch.tensor([ranges[c][0] for c in names])
        self.size = torch.tensor([ranges[c][1] - ranges[c][0] for c in names])
        self.p = torch.tensor([float(weights[c]) for c in names], dtype=torch.float64)
        self.num_samples = int(num_samples)

    def _total(self, world: int) -> int:
        return self.num_samples * world

    def _stream(self, n, g):
        which = torch.multinomial(self.p, n, replacement=True, generator=g)
        u = torch.rand(n, generator=g, dtype=torch.float64)
        return self.lo[which] + (u * self.size[which]).long().clamp_max(self.size[which] - 1)


class WindowSampler(ShardedSampler):
    """Windows ``0..n-1``: drawn uniformly with replacement, ``num_samples`` per rank and epoch
    (``replacement=True``); or one pass over all of them per epoch, shared by the ranks, shuffled
    (``shuffle=True``) or in order; a pass is padded by wrapping around so that every rank gets
    the same number of windows (as torch's DistributedSampler does)."""

    def __init__(self, n: int, shuffle: bool = True, replacement: bool = False, num_samples: int | None = None,
                 seed: int = 0, rank: int | None = None, world_size: int | None = None):
        super().__init__(seed, rank, world_size)
        if replacement and not shuffle:
            raise ValueError("drawing with replacement is random: replacement=True needs shuffle=True")
        if replacement and not num_samples:
            raise ValueError("drawing with replacement needs num_samples (per rank and epoch)")
        if num_samples is not None and not replacement:
            raise ValueError("num_samples is for drawing with replacement; a pass without it covers all windows")
        self.n, self.shuffle, self.replacement = int(n), bool(shuffle), bool(replacement)
        self.num_samples = int(num_samples) if replacement else None

    def _total(self, world: int) -> int:
        if self.replacement:
            return self.num_samples * world
        return -(-self.n // world) * world

    def _stream(self, n, g):
        if self.replacement:
            return torch.randint(self.n, (n,), generator=g)
        order = torch.randperm(self.n, generator=g) if self.shuffle else torch.arange(self.n)
        return order.repeat(-(-n // self.n))[:n]


def _worker_init(_):
    torch.set_num_threads(1)
    blosc.use_threads = False  # blosc's global thread pool is not fork-safe; one thread per worker anyway


def _collate(batch):
    return batch if isinstance(batch, dict) else default_collate(batch)  # __getitems__ batches already


def make_loader(store, collections: Iterable[str] | dict[str, float] | None = None, keys: Iterable[str] = (),
                seq_len: int = 16, batch_size: int = 32, num_workers: int = 2, weights: dict[str, float] | None = None,
                episodes=None, pad: bool = True, shuffle: bool = True, num_samples: int | None = None,
                seed: int = 0, cache_mb: float = 64, drop_last: bool = False) -> DataLoader:
    """A DataLoader of ``{"obs": {key: (B,T,...)}, "actions": (B,T,A), "pad_mask": (B,T)}``.
    ``collections`` may be a dict of mixture weights; ``episodes`` a list of (collection, episode)
    pairs (or a manifest DataFrame with those columns) restricting the windows.

    Windows come from a sampler that shards itself over the ranks of a distributed run (see
    ``ShardedSampler``): with ``num_samples`` (or mixture weights) each rank draws ``num_samples``
    windows per epoch, so an epoch has as many steps as in one process; without, the ranks share
    one pass over the windows. Lightning must not replace it (the trainer's
    ``use_distributed_sampler=False``, as ``nostra.workflows.training`` sets)."""
    if isinstance(collections, dict):
        weights, collections = dict(collections), list(collections)
    ds = SequenceDataset(store, collections, keys, seq_len, pad, episodes, cache_mb)
    if len(ds) == 0:
        raise ValueError(f"no windows of length {seq_len} (pad={pad}) in collections {ds.collections}")
    if weights is not None:
        sampler = MixtureSampler(ds.ranges, weights, num_samples or len(ds), seed)
    else:
        sampler = WindowSampler(len(ds), shuffle, shuffle and num_samples is not None,
                                num_samples if shuffle else None, seed)
    return DataLoader(ds, batch_size=batch_size, sampler=sampler, num_workers=num_workers, drop_last=drop_last,
                      worker_init_fn=_worker_init, collate_fn=_collate, persistent_workers=num_workers > 0)


def split_episodes(store, collections: Iterable[str], val_fraction: float = 0.1, seed: int = 0,
                   use_masks: bool = True) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """Hold out episodes for validation: a collection's robomimic ``valid`` mask where it has one,
    else a seeded random ``val_fraction`` of its episodes (at least one when it has two or more)."""
    store = store if isinstance(store, Store) else Store(store)
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    rng = np.random.default_rng(seed)
    train, val = [], []
    for c in collections:
        table = store.episodes(c)
        n = len(table)
        marked = np.array(["valid" in m for m in table["masks"]], bool)
        if use_masks and marked.any() and not marked.all():
            held = marked
        else:
            k = int(round(val_fraction * n))
            k = max(k, 1) if val_fraction > 0 and n > 1 else k
            held = np.zeros(n, bool)
            held[rng.permutation(n)[:k]] = True
        val += [(c, int(i)) for i in np.flatnonzero(held)]
        train += [(c, int(i)) for i in np.flatnonzero(~held)]
    return train, val


SPLIT_FILE = "episodes.json"  # a training run's split, beside its policy.ckpt


def save_split(path, train: list[tuple[str, int]], val: list[tuple[str, int]]) -> None:
    """The episodes a run trained on and held out, so later stages read them instead of recomputing."""
    Path(path).write_text(json.dumps({"train": [list(e) for e in train], "held_out": [list(e) for e in val]}))


def held_out_episodes(run_dir, collections: Iterable[str] | None = None) -> list[tuple[str, int]]:
    """The episodes a training run held out (its ``episodes.json``), optionally of some collections."""
    return run_episodes(run_dir, collections, "held_out")


SPLIT_PARTS = ("held_out", "train")


def run_episodes(run_dir, collections: Iterable[str] | None = None, part: str = "held_out") -> list[tuple[str, int]]:
    """The episodes a training run held out or trained on (``part``), optionally of some collections."""
    if part not in SPLIT_PARTS:
        raise ValueError(f"episode split part {part!r} unknown; valid: {', '.join(SPLIT_PARTS)}")
    path = Path(run_dir) / SPLIT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no episode split; the training run that made {run_dir} writes it "
                                "(runs trained before it existed: train again)")
    try:
        pairs = [(str(c), int(i)) for c, i in json.loads(path.read_text())[part]]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not an episode split ({{'train': [[collection, index], ...], "
                         f"'held_out': [...]}}): {e}") from e
    wanted = None if collections is None else set(collections)
    return [p for p in pairs if wanted is None or p[0] in wanted]
