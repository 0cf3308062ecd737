"""Package map: import names live under ``station.``; top-level folders map onto sub-packages."""

from setuptools import find_packages, setup

ROOTS = {"station": "station", "station.drivers": "drivers", "station.mocks": "mocks",
         "station.procedures": "procedures"}


def _packages() -> tuple[list[str], dict[str, str]]:
    packages, package_dir = [], {}
    for name, folder in ROOTS.items():
        package_dir[name] = folder
        packages.append(name)
        for sub in find_packages(folder):
            packages.append(f"{name}.{sub}")
    return packages, package_dir


packages, package_dir = _packages()
setup(
    packages=packages,
    package_dir=package_dir,
    # data the code finds through importlib.resources (shipped procedures' limits, built-in models, templates)
    package_data={"": ["*.yaml", "*.yml", "*.eds", "*.html", "*.css", "*.json", "*.txt"],
                  "station.kinematics": ["models/*.yaml"]},
    include_package_data=True,
)
