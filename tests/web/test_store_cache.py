"""The result cache is bounded by the memory its results hold, not only their number."""

import numpy as np
import pandas as pd

from app.web.store import ResultCache, approx_nbytes


class _Grid:
    def __init__(self, n):
        self.dg_mgal = np.zeros((n, n))
        self.dg_std_mgal = np.zeros((n, n))
        self.meta = {"crs": "EPSG:32657"}


def test_approx_nbytes_counts_arrays_tables_and_attributes():
    df = pd.DataFrame({"a": np.zeros(1000), "b": np.zeros(1000)})
    assert approx_nbytes(df) == df.memory_usage(index=True, deep=False).sum()
    assert approx_nbytes(_Grid(100)) == 2 * 100 * 100 * 8
    assert approx_nbytes((df, [np.zeros(10)], {"x": np.zeros(5)})) == approx_nbytes(df) + 80 + 40
    assert approx_nbytes("text") == 0


def test_cache_evicts_the_oldest_beyond_its_bytes_and_keeps_the_newest():
    cache = ResultCache(size=16, max_bytes=3 * 80_000 + 100)       # three 100x100 grids' dg (2 arrays each: 160 kB)
    built = []

    def build(k, n=100):
        built.append(k)
        return _Grid(n)

    for k in range(4):
        cache.get(k, lambda k=k: build(k))
    # 160 kB each: only one fits beside the newest within 240 kB
    cache.get(3, lambda: build(3))
    assert built == [0, 1, 2, 3]
    cache.get(0, lambda: build(0))
    assert built[-1] == 0                       # evicted, built again
    big = cache.get("big", lambda: build("big", 400))   # larger than the whole budget: kept alone
    assert big.dg_mgal.shape == (400, 400)
    cache.get("big", lambda: build("big-again"))
    assert built[-1] == "big"
    # the count bound still holds
    small = ResultCache(size=2, max_bytes=1 << 30)
    for k in range(3):
        small.get(k, lambda k=k: build(f"s{k}", 2))
    small.get(0, lambda: build("s0-again", 2))
    assert built[-1] == "s0-again"
