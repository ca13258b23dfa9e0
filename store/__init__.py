"""Content-hashed zarr artifact store: keys, atomic artifacts, run manifests, counters."""

from store.artifacts import Artifact, ArtifactStore
from store.keys import arrays_checksum, content_key, files_key
from store.manifest import Manifest, load_manifests

__all__ = ["Artifact", "ArtifactStore", "Manifest", "arrays_checksum", "content_key",
           "files_key", "load_manifests"]
