"""The launch rig's reading of ``ros2 launch`` output: which stops the watchdog ended."""

from launch_rig import teardown_hangs

# From a CI run: Fast DDS's participant deletion never returned in one observer.
HUNG = """\
[INFO] [landmark_observer-1]: process started with pid [18912]
[INFO] [landmark_observer-2]: process started with pid [18916]
[WARNING] [launch]: user interrupted with ctrl-c (SIGINT)
[INFO] [landmark_observer-1]: process has finished cleanly [pid 18912]
[landmark_observer-2] Timeout (0:00:10)!
[landmark_observer-2] Thread 0x00007f4db911d740 (most recent call first):
[landmark_observer-2]   File "/venv/site-packages/rclpy/node.py", line 1965 in destroy_node
[landmark_observer-2]   File "/ws/landmark_ros/ros/runner.py", line 256 in run
[ERROR] [landmark_observer-2]: process has died [pid 18916, exit code 1, cmd 'landmark_observer'].
"""


def test_a_watchdog_exit_inside_destroy_node_is_a_teardown_hang():
    assert teardown_hangs(HUNG) == {'landmark_observer-2'}


def test_a_hang_in_the_package_or_another_exit_code_is_not():
    in_package = HUNG.replace('rclpy/node.py", line 1965 in destroy_node',
                              'landmark_ros/nodes/fuser.py", line 207 in destroy_node')
    assert teardown_hangs(in_package) == set()
    assert teardown_hangs(HUNG.replace('exit code 1,', 'exit code 2,')) == set()
    assert teardown_hangs(HUNG.replace('[ERROR] [landmark_observer-2]: process has died',
                                       '[ERROR] [landmark_observer-1]: process has died')) == set()
    assert teardown_hangs(HUNG.replace('Timeout (0:00:10)!', 'Fatal Python error')) == set()
