"""Maps as a resource, the workers' side: a finished session's map as a map package (protocol.map_package) and a
package back as a GaussianMap (`package`), and the packages kept in Redis (`store`)."""

from .package import build_package, load_gaussian_map, package_from_map
from .store import add_version, read_package

__all__ = ["add_version", "build_package", "load_gaussian_map", "package_from_map", "read_package"]
