"""Content-hashed zarr artifact store: keys, atomic artifacts, run manifests, counters."""

from embody.store.artifacts import Artifact, ArtifactStore, CorruptArtifact
from embody.store.keys import arrays_checksum, content_key, files_key
from embody.store.manifest import Manifest, check_run_name, load_manifests

__all__ = ["Artifact", "ArtifactStore", "CorruptArtifact", "Manifest", "arrays_checksum", "content_key",
           "check_run_name", "files_key", "load_manifests"]
