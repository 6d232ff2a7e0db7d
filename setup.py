from glob import glob

from setuptools import find_packages, setup

PACKAGE = "spacerobot_planner"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    # colcon installs these; a pip (editable) install gets them from
    # `python -m spacerobot_planner.tools.ament_install --prefix <venv>`
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
    ],
    install_requires=["setuptools"],
    # colcon runs `colcon test` with pytest only when pytest is a declared test dependency
    extras_require={"test": ["pytest", "hypothesis"]},
    zip_safe=True,
    maintainer="spacerobot_planner maintainers",
    maintainer_email="maintainers@spacerobot-planner.invalid",
    description="Laplace-potential capture planner for a space robot, as a ROS 2 node",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "planner_node = spacerobot_planner.ros.planner_node:main",
            "mock_arm_node = spacerobot_planner.ros.mock_arm_node:main",
            "spacerobot-plan = spacerobot_planner.tools.cli:main",
            "spacerobot-demo = spacerobot_planner.tools.demo:main",
        ],
    },
)
