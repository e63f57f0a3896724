"""The helpers of ``training._distributed`` without processes: alone they are the identity; the
ordered split is checked by playing two ranks in one process; the batch SOM's ``reduce`` hook by
two threads that sum their halves of the data (against one process on all of it)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import pytest
import torch

import som_torch as st
from training._distributed import CallRecorder, Group, process_group
from training.errors import UserError


def test_alone_there_is_no_process_group(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    process_group.cache_clear()
    try:
        g = process_group()
    finally:
        process_group.cache_clear()
    assert (g.rank, g.world, g.main, g.distributed) == (0, 1, True, False)
    assert g.block(5) == range(5) and g.gather("x") == ["x"] and g.all_gather(3) == [3]
    assert list(g.ordered([1, 2, 3], lambda xs: (10 * x for x in xs))) == [10, 20, 30]

    def refuse() -> None:
        raise UserError("bad folder")

    with pytest.raises(UserError, match="bad folder"):
        g.on_main(refuse)


def test_a_bad_world_size_is_one_line(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "two")
    process_group.cache_clear()
    try:
        with pytest.raises(ValueError, match=r"\$WORLD_SIZE: expected an integer"):
            process_group()
    finally:
        process_group.cache_clear()


def test_blocks_cover_the_items_in_rank_order():
    for n in (0, 1, 5, 17):
        for world in (1, 2, 3, 7):
            blocks = [Group(rank=r, world=world).block(n) for r in range(world)]
            assert [i for b in blocks for i in b] == list(range(n))
            assert max(map(len, blocks)) - min(map(len, blocks)) <= 1


@dataclass(frozen=True)
class _Played(Group):
    """Rank ``rank`` of a world played in one process: ``gather`` hands rank 0 what the other
    ranks sent, round by round (their generators run first)."""

    sent: dict[int, list[Any]] = field(default_factory=dict, compare=False)

    def gather(self, obj: Any) -> list[Any] | None:
        if not self.main:
            self.sent.setdefault(self.rank, []).append(obj)
            return None
        k = len(self.sent.setdefault(0, []))
        self.sent[0].append(obj)
        return [obj] + [self.sent[r][k] for r in range(1, self.world)]


@pytest.mark.parametrize("n, world, per_round, granule", [(0, 2, 4, 1), (11, 2, 3, 1), (37, 3, 4, 1),
                                                           (37, 2, 16, 8), (9, 4, 8, 8), (100, 3, 10, 8)])
def test_ordered_gives_every_result_in_input_order(n, world, per_round, granule):
    items = list(range(n))
    seen: dict[int, list[int]] = {}

    def work(rank):
        def run(share):
            seen[rank] = list(share)
            return (x * x for x in share)
        return run

    sent: dict[int, list[Any]] = {}
    for r in range(1, world):
        assert list(_Played(rank=r, world=world, sent=sent).ordered(items, work(r), per_round=per_round,
                                                                     granule=granule)) == []
    got = list(_Played(rank=0, world=world, sent=sent).ordered(items, work(0), per_round=per_round, granule=granule))
    assert got == [x * x for x in items]
    assert sorted(x for share in seen.values() for x in share) == items
    # each rank's share is made of whole granules, in input order: batches of `granule` as one process makes
    for share in seen.values():
        starts = share[::granule]
        assert all(s % granule == 0 for s in starts) and share == sorted(share)


def test_call_recorder_replays_the_calls():
    class Writer:
        def __init__(self):
            self.log = []

        def add_scalar(self, tag, value, step):
            self.log.append((tag, value, step))

    rec = CallRecorder()
    rec.add_scalar("a", 1.0, 1)
    rec.add_scalar("b", 2.0, step=2)
    w = Writer()
    CallRecorder.replay(rec.take(), w)
    assert w.log == [("a", 1.0, 1), ("b", 2.0, 2)] and rec.take() == []


def test_batch_som_reduce_hook_equals_one_process():
    """Two 'ranks' (threads) train on halves of the data and all-reduce their sums through
    ``reduce``: the maps equal one process on all the data (float64 sums)."""
    g = torch.Generator().manual_seed(0)
    data = torch.rand(301, 4, generator=g, dtype=torch.float64)
    data[::7, 1] = float("nan")

    def new_som():
        som = st.SOM(st.Grid(4, 5), ["a", "b", "c", "p"], [True, True, True, False], batch_shape=(2,))
        som.fit_normalization(data, "standard")
        st.initialize(som, data, "random", seed=[4, 5])
        return som

    one = new_som()
    st.train_batch(one, data, epochs=4, sigma=(2.0, 0.5))

    barrier = threading.Barrier(2)
    box: list[torch.Tensor | None] = [None, None]

    def reduce_of(rank):
        def reduce(t):
            box[rank] = t.clone()
            barrier.wait()
            total = box[0] + box[1]
            barrier.wait()
            return total
        return reduce

    soms = [new_som(), new_som()]
    halves = [data[:150], data[150:]]
    threads = [threading.Thread(target=st.train_batch, args=(soms[r], halves[r]),
                                kwargs=dict(epochs=4, sigma=(2.0, 0.5), reduce=reduce_of(r))) for r in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for som in soms:
        torch.testing.assert_close(som.weights, one.weights, rtol=0, atol=1e-6)
