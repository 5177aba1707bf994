"""The window's observation book: counts, states removed with the landmarks they leave weak, and cached factors
that go with the observation lists they were built from."""
import gtsam
import numpy as np
import pytest

from services.backend.window.observations import ObservationBook

pytestmark = pytest.mark.unit


def test_book_keeps_counts_drops_weak_landmarks_and_rebuilds_factors_of_changed_lists():
    book = ObservationBook()
    xy = np.zeros(2)
    for state, lm, cam in ((0, 7, 0), (0, 7, 1), (1, 7, 0), (1, 8, 0), (2, 8, 0), (2, 9, 0)):
        book.add(state, lm, cam, xy)
    book.in_graph.update({7, 8})
    assert [book.count(lm) for lm in (7, 8, 9, 10)] == [3, 2, 1, 0]
    assert sorted(book.seen_at(1)) == [7, 8] and book.seen_at(2) == [8]  # 9 is not in the graph
    assert list(book.of_state(0)) == [7] and len(book.of_state(0)[7]) == 2
    built = []
    make = lambda: built.append(1) or gtsam.PriorFactorPoint3(gtsam.symbol("l", 7), np.zeros(3))
    f = book.factor(7, 0, 1, make)
    assert book.factor(7, 0, 1, make) is f and len(built) == 1  # cached
    book.set(7, 0, [book.by_landmark[7][0][0]])  # the list changed: its factors are built again
    assert book.factor(7, 0, 1, make) is not f and len(built) == 2
    assert book.remove_state(2) == [8, 9]  # left with fewer than two observations, in first-seen order
    assert 2 not in book.by_landmark[8] and book.count(9) == 0
    book.forget_if_unobserved(9)
    book.forget_if_unobserved(8)
    assert 9 not in book.by_landmark and 8 in book.by_landmark
