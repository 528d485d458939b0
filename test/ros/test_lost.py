"""``ros.lost.SequenceGaps``: messages lost, from the publication sequence numbers."""

from landmark_ros.ros.lost import SequenceGaps


def infos(*numbers):
    """Return MessageInfo dicts with these publication sequence numbers."""
    return [{'publication_sequence_number': n, 'source_timestamp': 0} for n in numbers]


class Publishers:
    """A publisher count per topic that records when it is asked."""

    def __init__(self, count=1):
        self.count, self.asked = count, 0

    def __call__(self, topic):
        self.asked += 1
        return self.count


def test_gaps_are_counted_across_batches_and_topics_apart():
    publishers = Publishers()
    gaps = SequenceGaps(publishers)
    assert gaps.lost('a', infos(7, 8, 9)) == 0      # the first number: nothing before it
    assert gaps.lost('b', infos(1, 2)) == 0
    assert gaps.lost('a', infos(12, 13, 20)) == 2 + 6
    assert gaps.lost('b', infos(3)) == 0
    assert gaps.lost('a', []) == 0
    assert gaps.lost('a', infos(21)) == 0
    assert publishers.asked == 1                     # only when a gap showed


def test_a_number_going_back_starts_over():
    gaps = SequenceGaps(Publishers())
    assert gaps.lost('a', infos(100, 101)) == 0
    assert gaps.lost('a', infos(1, 2, 4)) == 1      # a restarted publisher, then a gap


def test_gaps_are_not_counted_while_the_topic_has_several_publishers():
    publishers = Publishers(2)
    gaps = SequenceGaps(publishers)
    assert gaps.lost('a', infos(100, 5, 101, 6)) == 0
    publishers.count = 1
    assert gaps.lost('a', infos(9)) == 2


def test_messages_without_a_sequence_number_are_skipped():
    gaps = SequenceGaps(Publishers())
    assert gaps.lost('a', [None, {'publication_sequence_number': None}]) == 0
    assert gaps.lost('a', infos(3) + [None] + infos(5)) == 1
