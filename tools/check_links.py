#!/usr/bin/env python3
"""Checks that v2ce installs anywhere (issue 35): what it links and what its build pulls in.

    tools/check_links.py ELF [ELF ...]   the binaries' NEEDED entries: the C runtime only
    tools/check_links.py --deps          the default dependency graphs of the CLI and the
                                         Python package: no binding generator, no system library

An ELF may name only the C runtime (libc, libm, libgcc_s, the loader, and libpthread, libdl,
librt, libutil where a toolchain names them); anything else is a system library a user's
machine must have. The dependency graph (`cargo tree -e normal,build` of the default features)
must hold none of `clang-sys`, `bindgen`, `opencv*`, `*-sys` crates that link a system library
(`hdf5*-sys` and the like) or `pkg-config`: each stops a build on a machine with only the Rust
toolchain and a C compiler. One exception, by name: `pkg-config` as a build-dependency of
`zstd-sys` alone, which compiles its bundled zstd with the C compiler and asks pkg-config for a
system zstd only when `ZSTD_SYS_USE_PKG_CONFIG` is set (its `pkg-config` feature, which this
check also refuses, is off). Exits 1 with one line per breach.
"""
import re
import subprocess
import sys

# The C runtime: what every Linux program has.
RUNTIME = re.compile(
    r"^(libc\.so\.6|libm\.so\.6|libgcc_s\.so\.1|libpthread\.so\.0|libdl\.so\.2|librt\.so\.1"
    r"|libutil\.so\.1|ld-linux[-\w.]*\.so\.\d+)$"
)

# Crates of the build graph that need something beyond the Rust toolchain and a C compiler.
# `-sys` crates that only compile bundled C (zstd-sys, with `cc`) are fine.
FORBIDDEN = re.compile(r"^(clang-sys|bindgen|opencv[-\w]*|hdf5[-\w]*-sys|pkg-config) v")

PACKAGES = ["v2ce", "v2ce-python"]

# The crates that may depend on pkg-config (see the module docs), and the one way they would
# use it.
PKG_CONFIG_INERT_UNDER = {"zstd-sys"}


def tree(package, *args):
    return subprocess.run(
        ["cargo", "tree", "--locked", "-e", "normal,build", "--prefix", "none", "-p", package,
         *args],
        check=True, capture_output=True, text=True,
    ).stdout


def name_of(line):
    return line.split(" v")[0]


def needed(path):
    """The NEEDED entries of an ELF file, from `readelf -d`."""
    out = subprocess.run(
        ["readelf", "-d", path], check=True, capture_output=True, text=True
    ).stdout
    return re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", out)


def check_elves(paths):
    breaches = []
    for path in paths:
        libs = needed(path)
        if not libs:
            breaches.append(f"{path}: no NEEDED entry read (not a dynamic ELF?)")
        for lib in libs:
            if not RUNTIME.match(lib):
                breaches.append(f"{path}: links {lib}, which is not the C runtime")
        if not breaches:
            print(f"links: {path}: {', '.join(libs)}")
    return breaches


def check_deps():
    breaches = []
    for package in PACKAGES:
        bad = set()
        for line in tree(package).splitlines():
            if FORBIDDEN.match(line):
                bad.add(line.split(" (")[0])
        if any(name_of(c) == "pkg-config" for c in bad):
            # Who asks for it: allowed only where it stays unused.
            users = {name_of(l) for l in tree(package, "-i", "pkg-config", "--depth", "1")
                     .splitlines()[1:] if l.strip()}
            features = subprocess.run(
                ["cargo", "tree", "--locked", "-e", "features", "--prefix", "none", "-p",
                 package], check=True, capture_output=True, text=True).stdout
            if users <= PKG_CONFIG_INERT_UNDER and 'zstd-sys feature "pkg-config"' not in features:
                bad = {c for c in bad if name_of(c) != "pkg-config"}
        breaches += [f"{package}: the default build pulls {crate}" for crate in sorted(bad)]
        if not bad:
            print(f"links: {package}: no binding generator or system library in its build")
    return breaches


def main():
    args = sys.argv[1:]
    if not args:
        print(__doc__)
        return 2
    breaches = check_deps() if args == ["--deps"] else check_elves(args)
    for b in breaches:
        print(f"links: {b}")
    return 1 if breaches else 0


if __name__ == "__main__":
    sys.exit(main())
