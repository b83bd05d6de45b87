"""The one think scheduler (`wfnn_common.schedule`)."""

from wfnn_common.schedule import ThinkSchedule


def run(schedule, thinks_done, batch, stored=True, continuous=False):
    """Think as the scheduler says until it says 0; -> the think count reached."""
    while n := schedule.next_thinks(batch, thinks_done, stored, continuous):
        thinks_done += n
        schedule.advance(thinks_done)
        if continuous and thinks_done > 10_000:
            break
    return thinks_done


def test_owed_thinks_are_paid_in_batches_and_mark_each_clients_experiences_learned():
    s = ThinkSchedule()
    s.owe(30, "c1", 9)
    s.owe(20, "c2", 4)
    assert s.next_thinks(25, 0, stored=True) == 25 and s.budget == 25
    assert not s.advance(25) and s.learned_through == {}
    assert s.next_thinks(25, 25, stored=True) == 25 and s.advance(50)
    assert s.learned_through == {"c1": 9, "c2": 4} and s.settled(50)
    assert s.next_thinks(25, 50, stored=True) == 0


def test_extra_thinks_come_after_what_is_owed_and_delay_nothing_owed_later():
    s = ThinkSchedule()
    s.owe(10, "c1", 0)
    assert s.next_thinks(10, 0, stored=True, continuous=True) == 10
    assert s.next_thinks(10, 10, stored=True, continuous=True) == 10  # nothing owed: thinking on
    s.owe(10, "c1", 1)  # owed after 20 thinks done: done at 30
    assert s.next_thinks(10, 20, stored=True, continuous=True) == 10 and s.advance(30)
    assert s.learned_through == {"c1": 1}
    assert s.next_thinks(10, 30, stored=False, continuous=True) == 0  # nothing to replay


def test_after_a_reset_it_relearns_then_settles():
    s = ThinkSchedule()
    s.recover(100, 50)
    assert s.recovering(120) and not s.settled(120)
    assert run(s, 100, 20) == 160 and not s.recovering(160) and s.settled(160)


def test_a_resumed_learner_marks_its_stored_experiences_once_the_budget_is_paid():
    s = ThinkSchedule(learned_through={"c1": 3})
    s.resume(1000, 40, {"c1": 7, "c2": 2})
    assert s.learned_through == {"c1": 3}
    assert run(s, 1000, 16) == 1040 and s.learned_through == {"c1": 7, "c2": 2}


def test_without_a_client_nothing_is_followed():
    s = ThinkSchedule()
    for _ in range(1000):
        s.owe(5)
    assert s.budget == 5000 and run(s, 0, 64) == 5000 and s.learned_through == {} and s.settled(5000)
