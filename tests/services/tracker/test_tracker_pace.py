"""The keyframe ledger: whether keyframe_vl answered every keyframe, and at the requests' pace."""

from __future__ import annotations

from services.tracker.pace import KeyframeLedger, kept_up


def ledger(asked: list[float], answered: list[float | None]) -> KeyframeLedger:
    led = KeyframeLedger()
    for k, (t, a) in enumerate(zip(asked, answered, strict=True)):
        led.request(24 * k, t)
        if a is not None:
            led.masks(24 * k, a - 0.5)
            led.features(24 * k, a)
    return led


def test_a_keyframe_vl_that_keeps_up():
    stats = ledger([0.0, 10.0, 20.0, 30.0], [4.0, 14.5, 24.0, 34.2]).as_dict()
    assert stats["requested"] == stats["answered"] == stats["masks"] == 4
    assert stats["request_hz"] == 0.1 and abs(stats["answer_hz"] - 3 / 30.2) < 1e-6
    assert stats["latency_max_s"] == 4.5 and stats["latency_mean_s"] == 4.175
    assert kept_up(stats, 0.9)


def test_answers_that_fall_behind_fail_the_pace():
    # requests every 10 s, answers every 14 s: each keyframe later than the one before
    stats = ledger([0.0, 10.0, 20.0, 30.0], [14.0, 28.0, 42.0, 56.0]).as_dict()
    assert stats["answered"] == 4
    assert abs(stats["answer_hz"] - 1 / 14) < 1e-6
    assert not kept_up(stats, 0.9)
    assert kept_up(stats, 0.7)


def test_an_unanswered_keyframe_fails():
    stats = ledger([0.0, 10.0, 20.0], [4.0, 14.0, None]).as_dict()
    assert stats["requested"] == 3 and stats["answered"] == 2
    assert not kept_up(stats, 0.9)


def test_errors_stale_masks_and_timeouts_fail():
    for field in ("failed", "stale", "timed_out"):
        led = ledger([0.0, 10.0], [4.0, 14.0])
        assert kept_up(led.as_dict(), 0.9)
        setattr(led, field, 1)
        assert not kept_up(led.as_dict(), 0.9), field


def test_features_without_masks_do_not_count():
    led = KeyframeLedger()
    led.request(0, 0.0)
    led.features(0, 3.0)  # no masks recorded for it: not an answer
    led.masks(7, 1.0)  # never asked for
    stats = led.as_dict()
    assert stats["answered"] == 0 and stats["masks"] == 0
    assert not kept_up(stats, 0.9)


def test_one_keyframe_and_none():
    assert kept_up(ledger([0.0], [30.0]).as_dict(), 0.9)
    assert not kept_up(ledger([0.0], [None]).as_dict(), 0.9)
    # ground_truth mode asks for nothing
    assert kept_up(KeyframeLedger().as_dict(), 0.9)
