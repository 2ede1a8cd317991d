"""LeGO-LOAM (lego_loam_py) for a full ROS 2 install: ``ros2 launch lego_loam_py lego_loam.launch.py``.

The ROS 2 counterpart of the original's ``run.launch``: the four nodes as separate processes with one
parameter file (``share/lego_loam_py/config/params.yaml`` by default), ``use_sim_time`` for bag replay, and
optionally rviz2 with ``config/lego_loam.rviz`` (fixed frame ``map``). The original's two
static_transform_publisher nodes are not needed: transformFusion publishes map -> camera_init and
camera -> base_link on the latched /tf_static itself.

Arguments (``name:=value``):

* ``params_file``: ROS 2 parameter file for all four nodes;
* ``use_sim_time`` (default true, as the original): follow /clock, e.g. from ``ros2 bag play --clock`` or
  ``lego_loam_py play``;
* ``composed`` (default false): the four nodes in one process (``legoLoam``), their messages to each other in
  memory: the same topics and results for less CPU;
* ``rviz`` (default true): start rviz2 with ``rviz_config``;
* ``bag`` (default empty): replay this bag (ROS 1 ``.bag`` or ROS 2) with ``lego_loam_py play`` at ``rate``
  once the nodes subscribed; when it ends and ``shutdown_after_bag`` is true, everything is shut down
  ``drain`` seconds later (mapOptimization saves the map on the way out).

Without ros2 launch (ROS 2 from PyPI wheels) the same is ``lego_loam_py launch`` or
``python launch_scripts/lego_loam.py``.
"""

from launch.actions import DeclareLaunchArgument, EmitEvent, GroupAction, LogInfo, RegisterEventHandler, TimerAction
from launch.conditions import IfCondition, UnlessCondition
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

PACKAGE = 'lego_loam_py'
# The four executables in pipeline order (the original spells the third one mapOptmization).
NODES = ('imageProjection', 'featureAssociation', 'mapOptimization', 'transformFusion')
COMPOSED = 'legoLoam'  # the four in one process


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare(PACKAGE)
    params_file = LaunchConfiguration('params_file')
    use_sim_time = LaunchConfiguration('use_sim_time')
    bag = LaunchConfiguration('bag')
    sim_time = {'use_sim_time': ParameterValue(use_sim_time, value_type=bool)}

    arguments = [
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution([share, 'config', 'params.yaml']),
            description='ROS 2 parameter file for the four nodes',
        ),
        DeclareLaunchArgument(
            'use_sim_time',
            default_value='true',
            choices=['true', 'false'],
            description='follow /clock (bag replay) instead of the wall clock',
        ),
        DeclareLaunchArgument(
            'composed',
            default_value='false',
            choices=['true', 'false'],
            description='the four nodes in one process, their messages to each other in memory',
        ),
        DeclareLaunchArgument('rviz', default_value='true', choices=['true', 'false'], description='start rviz2'),
        DeclareLaunchArgument(
            'rviz_config',
            default_value=PathJoinSubstitution([share, 'config', 'lego_loam.rviz']),
            description='rviz2 configuration',
        ),
        DeclareLaunchArgument(
            'bag', default_value='', description='bag to replay with lego_loam_py play (empty: none; play it yourself)'
        ),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate of the bag'),
        DeclareLaunchArgument(
            'shutdown_after_bag',
            default_value='true',
            choices=['true', 'false'],
            description='shut everything down once the bag is played',
        ),
        DeclareLaunchArgument(
            'drain', default_value='3.0', description='seconds between the end of the bag and the shutdown'
        ),
    ]

    composed = LaunchConfiguration('composed')
    nodes = [
        Node(
            package=PACKAGE,
            executable=name,
            name=name,
            output='screen',
            parameters=[params_file, sim_time],
            condition=UnlessCondition(composed),
        )
        for name in NODES
    ]
    # (No name: it would rename each of the four nodes in the process.)
    nodes.append(
        Node(
            package=PACKAGE,
            executable=COMPOSED,
            output='screen',
            parameters=[params_file, sim_time],
            condition=IfCondition(composed),
        )
    )

    rviz = Node(
        package='rviz2',
        executable='rviz2',
        name='rviz2',
        output='log',
        arguments=['-d', LaunchConfiguration('rviz_config')],
        parameters=[sim_time],
        condition=IfCondition(LaunchConfiguration('rviz')),
    )

    has_bag = IfCondition(PythonExpression(["'", bag, "' != ''"]))
    player = Node(
        package=PACKAGE,
        executable='lego_loam_py',
        name='player',
        output='screen',
        arguments=['play', bag, '--rate', LaunchConfiguration('rate'), '--wait-for-subscribers', '30', '--no-progress'],
        condition=has_bag,
    )
    # GroupAction carries the condition: RegisterEventHandler takes none in older launch releases.
    shutdown_after_bag = GroupAction(
        condition=IfCondition(
            PythonExpression(["'", bag, "' != '' and '", LaunchConfiguration('shutdown_after_bag'), "' == 'true'"])
        ),
        actions=[
            RegisterEventHandler(
                OnProcessExit(
                    target_action=player,
                    on_exit=[
                        LogInfo(msg=['the bag was played; shutting down in ', LaunchConfiguration('drain'), ' s']),
                        TimerAction(
                            period=LaunchConfiguration('drain'),
                            actions=[EmitEvent(event=Shutdown(reason='the bag was played'))],
                        ),
                    ],
                )
            )
        ],
    )

    return LaunchDescription(arguments + nodes + [rviz, player, shutdown_after_bag])
