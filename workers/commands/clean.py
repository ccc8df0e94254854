"""``schlieren clean STORE``: delete the store's cache of derived files (``STORE.cache``).

The tomography geometry (the projection of every basis function into every camera) is
built once per run and memory-mapped by the tomography tasks; it lives beside the store,
outside the Zarr hierarchy, and is often larger than the results. Cleaning removes it and
clears the ``geometry`` stage's completion marker, so a later run on the store (a resume,
more frames) builds it again when it needs it. The results are untouched.
"""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser("clean", help="delete a result store's cache (the tomography geometry)",
                       description=__doc__.split("\n", 1)[1].strip().replace("``", ""))
    p.add_argument("store", help="result store (Zarr folder)")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.storage.arrays_cache import cache_root, remove_cache
    from schlieren.storage.store import ResultStore

    from schlieren.workers.run import store_lease

    store = ResultStore.open(args.store, mode="r+")  # a one-line error if it is not a result store
    with store_lease(args.store, purpose="clean"):  # never under a running run's feet
        freed = remove_cache(args.store)
        if "geometry" in store.stages():
            store.unmark("geometry")
    print(f"removed {cache_root(args.store)} ({freed / 2 ** 20:.1f} MiB); results in {args.store} kept")
    return 0
