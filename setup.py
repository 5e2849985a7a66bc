from glob import glob

from setuptools import find_packages, setup

PACKAGE = "semcal_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*", "semcal_tools", "semcal_tools.*"]),
    # the geometric point labeller's forest (semcal_tools/train_point_labeller.py writes it)
    package_data={f"{PACKAGE}.segmentation": ["data/*.npz"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/config/models", glob("config/models/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="semcal_ros developers",
    maintainer_email="dev@semcal.invalid",
    description="Target-free camera extrinsic calibration against a labelled lidar map",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "semcal = semcal_ros.cli:main",
            "map_builder = semcal_ros.ros.nodes.map_builder:main",
            "cloud_segmenter = semcal_ros.ros.nodes.cloud_segmenter:main",
            "image_segmenter = semcal_ros.ros.nodes.image_segmenter:main",
            "calibrator = semcal_ros.ros.nodes.calibrator:main",
            "bag_player = semcal_ros.ros.nodes.bag_player:main",
            "calibration_monitor = semcal_ros.ros.nodes.calibration_monitor:main",
        ],
    },
)
