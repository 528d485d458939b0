"""Take the messages already waiting on a subscription, to handle them in one batch."""


def take_waiting(subscription, msg_type, limit, raw=False):
    """
    Take up to ``limit`` messages already queued on ``subscription``, without waiting.

    A node that handles a burst of messages in one callback pays the executor's
    per-message overhead (wait set, dispatch) once; the rest is taken directly,
    as rclpy's own ``wait_for_message`` does.

    Parameters
    ----------
    subscription : rclpy.subscription.Subscription
        A subscription of the calling node.
    msg_type : type
        Its message type.
    limit : int
        Most messages to take.
    raw : bool
        Take the serialized bytes (as a ``raw=True`` subscription delivers them).

    Returns
    -------
    list
        The messages (or their bytes), oldest first.

    """
    taken = []
    if limit <= 0:
        return taken
    handle = subscription.handle
    with handle:
        while len(taken) < limit:
            message_and_info = handle.take_message(msg_type, raw)
            if message_and_info is None:
                break
            taken.append(message_and_info[0])
    return taken
