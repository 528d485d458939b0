"""Input subscriptions with plain rclpy: publishers whose QoS cannot reach them."""

from landmark_ros.ros import qos


class IncompatiblePublishers:
    """
    Find each publisher whose QoS cannot reach an input subscription, once.

    The fast inputs have no QoS event handlers (``fast_io``), so nothing tells the
    node of a publisher it will never hear; ``check`` asks the graph instead
    (``Node.get_publishers_info_by_topic``) and compares each publisher's QoS with
    the subscription's (``qos.incompatible_policy``). Each publisher (by GID) is
    reported once.
    """

    def __init__(self, node):
        self._node = node
        self._seen = set()

    def check(self, inputs):
        """
        Return the newly found incompatible publishers of ``inputs``.

        Parameters
        ----------
        inputs : iterable of (object, rclpy.subscription.Subscription)
            ``(source, subscription)``: the source is handed back as it is.

        Returns
        -------
        list of (object, str, str)
            ``(source, publisher node name, policy)``.

        """
        found = []
        for source, subscription in inputs:
            for info in self._node.get_publishers_info_by_topic(subscription.topic_name):
                gid = bytes(info.endpoint_gid)
                if gid in self._seen:
                    continue
                policy = qos.incompatible_policy(subscription.qos_profile, info.qos_profile)
                if policy is not None:
                    self._seen.add(gid)
                    name = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
                    found.append((source, name, policy))
        return found
