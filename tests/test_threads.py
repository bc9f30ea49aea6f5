"""kpd.viewer.threads: the drawing path's pool and the split of a pass in halves."""

import threading

import numpy as np

from kpd.viewer.threads import draw_pool, in_halves


def test_a_pass_in_halves_covers_every_item_once_on_at_most_two_threads():
    for n in (0, 5, 199_999, 200_000, 300_001):
        seen = np.zeros(n, dtype=np.int64)
        threads = set()

        def kernel(lo, hi, out):
            threads.add(threading.get_ident())
            out[lo:hi] += 1

        in_halves(kernel, n, seen)
        assert (seen == 1).all()
        assert len(threads) <= 2


def test_the_pool_is_made_once():
    assert draw_pool() is draw_pool()
