"""The vehicle worker's tick breakdown (status line ``tick_parts_ms``, printed by
`skyfuse bench live`): the timed bus forwards everything and sums its publish time; the
percentiles are the samples' own."""
import numpy as np

from vehicles import process as vp


class _Bus:
    faults = ("a rule",)

    def __init__(self):
        self.got = []

    def publish(self, key, msg):
        self.got.append((key, msg))
        return "ok"


def test_timed_publish_forwards_and_sums_the_publish_time():
    ticks = iter([0.0, 0.25, 1.0, 1.5])  # two publishes: 0.25 s and 0.5 s on the fake timer
    bus = _Bus()
    tb = vp._TimedPublish(bus, lambda: next(ticks))
    assert tb.publish("k1", 1) == "ok" and tb.publish("k2", 2) == "ok"
    assert bus.got == [("k1", 1), ("k2", 2)]
    assert tb.publish_s == 0.75
    assert tb.faults == ("a rule",)  # what VehicleGroup reads of its bus (publishes_columnar)


def test_timed_publish_counts_a_failed_publish_too():
    ticks = iter([2.0, 2.5])

    class Broken(_Bus):
        def publish(self, key, msg):
            raise OSError("session closed")
    tb = vp._TimedPublish(Broken(), lambda: next(ticks))
    try:
        tb.publish("k", 0)
    except OSError:
        pass
    assert tb.publish_s == 0.5


def test_percentiles_are_the_order_statistics_of_the_samples():
    rng = np.random.default_rng(7)
    xs = rng.exponential(0.01, 500)
    d = vp._pcts_ms(xs)
    s = np.sort(xs)
    assert d["p50"] == 1e3 * s[250] and d["p99"] == 1e3 * s[int(0.99 * 500)] and d["max"] == 1e3 * s[-1]
    assert set(vp.TICK_PARTS) == {"input", "world", "bus_put", "streams", "cpu"}
