"""
landmark_fuser: the landmark observations of several robots in, one fused map out.

Subscribes every topic of ``input_topics`` (landmark clouds, one source each),
queues their rows and fuses them by landmark ID in batches with
``landmark_ros.fuser.fuser.Fuser``; every topic of ``partial_observation_topics``
(partial observations: range-only and bearing-only, one source each) too. Publishes the
confirmed map on
``fused_landmarks`` (transient local: late subscribers get it), the landmarks changed
since the last update on ``fused_landmark_updates``, RViz markers on
``fused_markers`` and ``/diagnostics``; services ``~/reset`` and ``~/save``. With
``map_file`` set the map is loaded at start and saved atomically.
"""

import sys
from types import SimpleNamespace

from diagnostic_msgs.msg import DiagnosticArray
from landmark_ros.nodes._fuser_outputs import MapOutputs
from landmark_ros.nodes.start import finish, imported, lazy
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.ros import diagnostics, fast_io, guard, qos, runner
from landmark_ros.ros.cloud import CloudError
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.lost import describe
from landmark_ros.ros.params import declare_config, keep_in_sync
from landmark_ros.ros.subscriptions import IncompatiblePublishers
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

# Imported when the node is built, not at module import (scipy: a second or more).
pipeline = lazy('landmark_ros.fuser.fuser')
schemas = lazy('landmark_ros.ros.schemas')


class LandmarkFuser(Node):
    """Fuse the landmark observations of a team of robots by landmark ID."""

    def __init__(self, **kwargs):
        super().__init__('landmark_fuser', **kwargs)
        config = declare_config(self, FuserConfig)
        fast = fast_io.declare_switch(self)
        landmark_topics = list(config.input_topics)
        partial_topics = [topic for topic in config.partial_observation_topics if topic]
        self._source_of = {topic: self.resolve_topic_name(topic)
                           for topic in landmark_topics + partial_topics}
        overrides = qos.input_overrides()
        self.landmark_inputs = fast_io.Inputs(self, fast_io.InputSpec(
            PointCloud2, landmark_topics, qos.reliable_input(config.input_depth),
            lambda: self.config.max_batch_messages,
            lambda: 0.25 * self.config.update_period_s, across=True, raw_clouds=True,
            qos_overriding_options=overrides, on_lost=self.on_lost),
            self.on_landmarks, self._guard, fast)
        self.partial_inputs = fast_io.Inputs(self, fast_io.InputSpec(
            PointCloud2, partial_topics, qos.reliable_input(config.input_depth),
            lambda: self.config.max_batch_messages, qos_overriding_options=overrides,
            on_lost=self.on_lost), self.on_partial, self._guard, fast)
        self.outputs = MapOutputs(self, config)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     qos.DIAGNOSTICS)
        self.create_service(Trigger, '~/reset', self._guard(self.on_reset))
        self.create_service(Trigger, '~/save', self._guard(self.on_save))
        self._incompatible = IncompatiblePublishers(self)
        keep_in_sync(self, lambda: self.fuser.config, self._apply_config)
        self.create_timer(config.update_period_s, self._guard(self.fuse_queued))
        self.create_timer(self.outputs.period_s, self._guard(self.publish_outputs))
        self.create_timer(config.diagnostics_period_s, self._guard(self.publish_diagnostics))
        if config.map_file and config.autosave_period_s > 0.0:
            self.create_timer(config.autosave_period_s, self._guard(self.autosave))
        # The endpoints first, then the fusion code (imports: scipy, the map; the map
        # file): no callback runs before the constructor returns, and what arrives
        # meanwhile waits in the input queues (input_depth deep, reliable).
        if not imported(self, lambda: pipeline.Fuser):
            return      # a stop signal came: the runner ends the node without spinning
        self.fuser = pipeline.Fuser(
            config, [self._source_of[topic] for topic in landmark_topics], self.get_logger(),
            [self._source_of[topic] for topic in partial_topics])
        self.fuser.load()

    def _guard(self, callback, what=None):
        # Callbacks created before the fuser exists count into it once it does.
        counters = SimpleNamespace(add=lambda *args: self.fuser.counters.add(*args))
        return guard.guarded(self, counters, callback, what or callback.__name__)

    @property
    def config(self):
        """Return the parameters in force (the fuser's)."""
        return self.fuser.config

    @property
    def sources(self):
        """Return the fuser's sources by ``input_topics`` entry (names: resolved topics)."""
        return {topic: self.fuser.sources[self._source_of[topic]]
                for topic in self.landmark_inputs.subscriptions}

    def _apply_config(self, config):
        self.fuser.reconfigure(config)
        self.outputs.markers_stale = True

    # Input ---------------------------------------------------------------------

    def on_lost(self, topic, count):
        """Count ``count`` messages of ``topic`` that went missing on the way."""
        self.fuser.reject(self._source_of[topic], 'messages_lost', count,
                          describe(topic, count))

    def on_landmarks(self, bursts):
        """
        Read the landmark clouds of ``bursts`` (``[(topic, clouds)]``) and queue their rows.

        The clouds of every topic are read together (``schemas.read_landmark_clouds``) and
        queued as one burst (``Fuser.add_landmark_bursts``); a cloud that cannot be read
        is counted against its source and dropped.
        """
        now = self.get_clock().now().nanoseconds
        parsed = []
        for topic, clouds in bursts:
            for cloud in clouds:
                if isinstance(cloud, CloudError):
                    self._drop_cloud(self._source_of[topic], cloud)
                else:
                    parsed.append((self._source_of[topic], cloud))
        out = {}
        for (source, cloud), read in zip(parsed, schemas.read_landmark_clouds(
                [cloud for _, cloud in parsed])):
            if isinstance(read, CloudError):
                self._drop_cloud(source, read)
                continue
            rows, extras = read
            out.setdefault(source, []).append(pipeline.LandmarkMessage(
                stamp_ns(cloud.header.stamp), rows.ids, rows.m, rows.P, rows.P_dep,
                cloud.header.frame_id, extras.classes, extras.scan))
        self.fuser.add_landmark_bursts(list(out.items()), now)

    def fuse_queued(self):
        """Fuse every queued row, in arrival order, in one batch."""
        self.fuser.fuse_queued()

    def _drop_cloud(self, source, error):
        self.fuser.reject(source, 'messages_in')
        self.fuser.reject(source, error.reason, 1, f'message dropped: {error}')

    def on_partial(self, bursts):
        """Read partial-observation clouds (``[(topic, clouds)]``) and queue their rows."""
        now = self.get_clock().now().nanoseconds
        for topic, clouds in bursts:
            source = self._source_of[topic]
            for cloud in clouds:
                try:
                    columns = schemas.read_partial_observations(cloud)
                except CloudError as error:
                    self._drop_cloud(source, error)
                    continue
                self.fuser.add_partial_observations(source, stamp_ns(cloud.header.stamp),
                                                    columns, cloud.header.frame_id, now)

    # Output --------------------------------------------------------------------

    def publish_outputs(self):
        """Publish the map updates, the map and the markers due at this tick."""
        self.outputs.publish(self.fuser)

    def publish_diagnostics(self):
        """Publish the fuser's status and one status per source on /diagnostics."""
        inputs = [(self._source_of[topic], sub) for inputs in (
            self.landmark_inputs, self.partial_inputs) for topic, sub in
            inputs.subscriptions.items()]
        for source, name, policy in self._incompatible.check(inputs):
            self.fuser.reject(source, 'incompatible_qos', 1,
                              f'publisher {name} offers incompatible QoS ({policy}): its '
                              'messages are not received')
        name = self.get_fully_qualified_name()
        diagnostics.publish(self, self.diagnostics_pub, [
            diagnostics.to_msg(status, name, self.get_namespace())
            for status in self.fuser.statuses(self.get_clock().now().nanoseconds)])

    # Services and persistence ----------------------------------------------------

    def on_reset(self, request, response):
        """Clear the map, the queues and the markers."""
        count = self.fuser.reset()
        self.outputs.clear(self.fuser)
        self.get_logger().info(f'map reset: {count} landmarks cleared')
        response.success, response.message = True, f'cleared {count} landmarks'
        return response

    def on_save(self, request, response):
        """Save the map to ``map_file`` now."""
        if not self.config.map_file:
            response.success, response.message = False, 'map_file is not set'
            return response
        response.success = self.fuser.save()
        response.message = (f'saved {len(self.fuser.map)} landmarks to {self.config.map_file}'
                            if response.success else 'save failed: see the log')
        return response

    def autosave(self):
        """Save the map if it changed since the last save."""
        if self.fuser.unsaved:
            self.fuser.save()

    def destroy_node(self):
        """Save the map (when a map file is set) before going away."""
        fuser = getattr(self, 'fuser', None)     # None: stopped before it was built
        if fuser is not None and fuser.config.map_file and fuser.unsaved:
            fuser.save()
        return super().destroy_node()


def main(args=None):
    """Run the node until shutdown; the map is saved on the way out."""
    return runner.run(LandmarkFuser, 'landmark_fuser', args)


if __name__ == '__main__':
    sys.exit(finish(main()))
