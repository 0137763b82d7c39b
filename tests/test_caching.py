"""``fsswarp.caching.Remembered``: bounded, least recently used first, and one value per key
where threads make it at once."""

import threading

from fsswarp.caching import Remembered


def test_the_least_recently_used_goes_first_beyond_the_size():
    cache, made = Remembered(3), []

    def make(key):
        return lambda: made.append(key) or [key]

    first = cache.get("a", make("a"))
    for key in "bc":
        cache.get(key, make(key))
    assert cache.get("a", make("a")) is first and made == ["a", "b", "c"]  # kept, and now the latest
    cache.get("d", make("d"))  # drops "b", the least recently used
    assert len(cache) == 3
    cache.get("a", make("a"))
    cache.get("b", make("b"))
    assert made == ["a", "b", "c", "d", "b"]
    cache.clear()
    assert len(cache) == 0 and cache.get("a", make("a")) is not first


def test_threads_that_make_one_key_at_once_all_get_the_value_kept_first():
    cache, started, results = Remembered(4), threading.Barrier(8), []

    def make():
        started.wait()  # every thread is making the value before any keeps it
        return object()

    threads = [threading.Thread(target=lambda: results.append(cache.get("key", make))) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(results) == 8 and all(value is results[0] for value in results)
    assert cache.get("key", object) is results[0]
