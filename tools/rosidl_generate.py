"""Generate the C and Python sources of a message-only ROS 2 interface package.

Used by tools/build_tf2_msgs.sh. It does what ``rosidl_generate_interfaces()`` does at CMake
time, for the C type support stack only (rosidl_generator_c, rosidl_generator_py and the
rosidl_typesupport_c / _fastrtps_c / _introspection_c type supports), by calling the generator
classes that the pip-installed rosidl packages provide. The ``rosidl generate`` command would
do the same, but it refuses to run when a generator is registered twice, which the ROS wheels
do (both an .egg-info and a .dist-info declare the entry points).

Usage: python rosidl_generate.py PACKAGE SOURCE_DIR INCLUDE_SHARE_DIR OUTPUT_DIR

SOURCE_DIR holds msg/*.msg; INCLUDE_SHARE_DIR is the share/ directory with the .idl files of
the dependencies (e.g. .venv/share). OUTPUT_DIR receives one folder per generator, each with a
PACKAGE/ subfolder laid out as the headers and modules are installed.
"""

from __future__ import annotations

import inspect
import pathlib
import sys

from rosidl_cli.command.hash.api import generate_type_hashes
from rosidl_cli.command.translate.api import translate
from rosidl_generator_c.cli import GenerateC
from rosidl_generator_py.cli import GeneratePython
from rosidl_typesupport_c.cli import GenerateCTypesupport
from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

GENERATORS = {
    "generator_c": GenerateC,
    "generator_py": GeneratePython,
    "typesupport_c": GenerateCTypesupport,
    "typesupport_fastrtps_c": GenerateFastRTPSCTypesupport,
    "typesupport_introspection_c": GenerateIntrospectionCTypesupport,
}


def main(argv: list[str]) -> int:
    if len(argv) != 4:
        print(__doc__, file=sys.stderr)
        return 2
    package, source, share, output = argv
    source_dir = pathlib.Path(source).resolve()
    out = pathlib.Path(output).resolve()
    msgs = sorted(p.relative_to(source_dir).as_posix() for p in source_dir.glob("msg/*.msg"))
    if not msgs:
        print(f"no msg/*.msg under {source_dir}", file=sys.stderr)
        return 1
    idl_files = translate(
        package_name=package,
        interface_files=[f"{source_dir}:{m}" for m in msgs],
        include_paths=[share],
        output_format="idl",
        output_path=out / "idl",
    )
    type_descriptions = generate_type_hashes(
        package_name=package,
        interface_files=idl_files,
        include_paths=[share],
        output_path=out / "type_description",
    )
    for name, cls in GENERATORS.items():
        generator = cls(name)
        kwargs = {}
        if "type_description_files" in inspect.signature(generator.generate).parameters:
            kwargs["type_description_files"] = type_descriptions
        generator.generate(package, idl_files, [share], output_path=out / name / package, **kwargs)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
