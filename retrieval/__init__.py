"""Episode retrieval: embeddings (object/skill, camera/scene) and faiss indices over them.

    from retrieval import EmbeddingCache, embed_store, build_index, update_index, rerank
    obj = embed_store(store, "obj_skill")           # {collection: Embeddings}, cached beside the store
    index, _ = update_index(path, obj)              # adds new collections, rebuilds changed ones
    ids, scores = index.search(query, k)            # obj/skill retrieval; index.entries(ids) names them
    # "all": re-rank those hits by camera pose and placement
    order, _ = rerank(target_scene, vectors_for(embed_store(store, "scene"), index.entries(ids)), "l2")
"""

from retrieval.embed import (EmbeddingCache, EmbeddingError, Embeddings, TextEmbedder, embed_collection, embed_store,
                             fingerprint, store_frames, vectors_for)
from retrieval.index import EpisodeIndex, IndexConfig, IndexMismatchError, build_index, rerank, update_index

__all__ = ["EmbeddingCache", "EmbeddingError", "Embeddings", "TextEmbedder", "embed_collection", "embed_store",
           "fingerprint", "store_frames", "vectors_for", "EpisodeIndex", "IndexConfig", "IndexMismatchError",
           "build_index", "rerank", "update_index"]
