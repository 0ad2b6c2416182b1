"""``phirie_jax.threads.map_on_cores``: the plain loop's results, in order, on several threads."""

import threading

import pytest

from phirie_jax.threads import map_on_cores


def test_results_come_back_in_the_order_of_the_items(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    names = set()

    def slow_square(x):
        names.add(threading.current_thread().name)
        threading.Event().wait(0.01 * (10 - x))  # later items finish first
        return x * x

    assert map_on_cores(slow_square, range(10), "squares") == [x * x for x in range(10)]
    assert len(names) > 1 and all(n.startswith("squares") for n in names)


def test_one_core_or_one_item_runs_on_the_calling_thread(monkeypatch):
    here = threading.current_thread().name
    assert map_on_cores(lambda _: threading.current_thread().name, [0]) == [here]
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    assert map_on_cores(lambda _: threading.current_thread().name, range(3)) == [here] * 3
    assert map_on_cores(lambda x: x, []) == []


def test_an_items_exception_is_raised_as_the_loop_would(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)

    def fails_on_three(x):
        if x == 3:
            raise ValueError("three")
        return x

    with pytest.raises(ValueError, match="three"):
        map_on_cores(fails_on_three, range(6))
