"""The result store: one Zarr v3 group per run (SPEC section 2, docs/design.md).

The coordinator creates the group and every array up front
(:meth:`ResultStore.create`, the *template*); tasks then open the store by path, write
whole chunks (:meth:`ResultStore.write` refuses partial-chunk regions, which lose data
under concurrent writers) and set their completion marker last
(:meth:`ResultStore.mark_done`). Markers, not chunk presence, mean "done": a killed task
can leave some of its chunks written.

Integrity (``storage/integrity.py``): every array ends its codecs with ``crc32c``, the data
arrays store even fill-valued chunks (``write_empty_chunks=True``), and the root attribute
``integrity`` records which stage's marker covers each array. A read never returns a
chunk that fails its checksum or that is missing under a set marker: it raises
:class:`~schlieren.storage.errors.ChunkError` naming the array and the chunk. Stores of
older versions (no ``integrity``) are read without these checks and are not resumed.

An existing path is never overwritten or deleted: :meth:`create` on an existing store
resumes it only if its ``fingerprint`` attribute (a hash of session + configuration,
see :func:`fingerprint`) equals the caller's; anything else raises
:class:`~schlieren.storage.errors.StoreError` naming the path.

The package: :mod:`.result_store` (:class:`ResultStore`: opening, access, reads and writes),
:mod:`.template` (creating the template, resuming an existing store), :mod:`.writes` (the
three ways a chunk is written: its file in a folder store, one PUT to object storage,
or zarr), :mod:`.markers` (completion markers), :mod:`.chunks` (listing and checking
stored chunks for :func:`~schlieren.storage.integrity.scan_store`), :mod:`.attrs` (the
root attributes as JSON) and :mod:`.group` (the zarr group, every read checked).
"""

from schlieren.storage.store.attrs import JSON_ATTRS, decode_attrs, fingerprint, to_json
from schlieren.storage.store.result_store import ResultStore, remove_store
from schlieren.storage.store.template import check_store_target

__all__ = ["ResultStore", "fingerprint", "to_json", "decode_attrs", "JSON_ATTRS", "remove_store",
           "check_store_target"]
