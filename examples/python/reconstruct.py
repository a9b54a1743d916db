#!/usr/bin/env python3
"""Reconstructs a frame bundle through libgdrecon's C API with ctypes (no other dependency).

    python3 examples/python/reconstruct.py [--lib PATH] FRAME.exr OUT_PREFIX

Reads the bundle with gdr_frame_read, runs every method (gdr_method_name), reports progress
through a Python callback and writes OUT_PREFIX_<method>.pfm. The library is found with --lib,
else $GDRECON_LIB, else target/release/libgdrecon.so of this repository.
"""

import argparse
import array
import ctypes as C
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
GDR_ERROR_NONE = 0
LAYERS = ["color", "dx", "dy", "variance", "albedo", "normal", "depth"]
PROGRESS_FN = C.CFUNCTYPE(C.c_bool, C.c_void_p, C.c_double)


class GdrError(RuntimeError):
    """A failed gdrecon call: status code and the library's message."""

    def __init__(self, lib, call, code):
        message = C.c_char_p()
        lib.gdr_get_error(C.byref(message))
        name = lib.gdr_error_name(code).decode()
        super().__init__(f"{call}: {name}: {(message.value or b'').decode()}")
        self.code = code


def load(path):
    """Opens the shared library and declares the functions used here."""
    lib = C.CDLL(path)
    sz, f32, p = C.c_size_t, C.c_float, C.c_void_p
    status = C.c_uint32
    sigs = {
        "gdr_version": (C.c_uint32, []),
        "gdr_get_error": (status, [C.POINTER(C.c_char_p)]),
        "gdr_error_name": (C.c_char_p, [C.c_uint32]),
        "gdr_method_name": (C.c_char_p, [C.c_uint32]),
        "gdr_context_new": (status, [C.POINTER(p)]),
        "gdr_context_set_int": (status, [p, C.c_char_p, C.c_int32]),
        "gdr_context_commit": (status, [p]),
        "gdr_context_release": (status, [C.POINTER(p)]),
        "gdr_frame_read": (status, [C.c_char_p, C.POINTER(p)]),
        "gdr_frame_get_info": (status, [p, C.POINTER(sz), C.POINTER(sz), C.POINTER(f32)]),
        "gdr_frame_get_layer": (status, [p, C.c_char_p, C.POINTER(C.POINTER(f32)), C.POINTER(sz)]),
        "gdr_frame_release": (status, [C.POINTER(p)]),
        "gdr_filter_new": (status, [p, C.c_char_p, C.POINTER(p)]),
        "gdr_filter_set_float": (status, [p, C.c_char_p, f32]),
        "gdr_filter_set_image": (status, [p, C.c_char_p, p, sz, sz, sz, sz, sz]),
        "gdr_filter_set_image_planar": (status, [p, C.c_char_p, p, sz, sz, sz, sz, sz]),
        "gdr_filter_set_progress_callback": (status, [p, PROGRESS_FN, p]),
        "gdr_filter_commit": (status, [p]),
        "gdr_filter_execute": (status, [p]),
        "gdr_filter_get_report": (status, [p, C.POINTER(C.c_char_p)]),
        "gdr_filter_release": (status, [C.POINTER(p)]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    return lib


def call(lib, name, *args):
    code = getattr(lib, name)(*args)
    if code != GDR_ERROR_NONE:
        raise GdrError(lib, name, code)


def write_pfm(path, rgb, width, height):
    with open(path, "wb") as f:
        f.write(f"PF\n{width} {height}\n-1.0\n".encode())
        row = width * 3
        for y in reversed(range(height)):
            f.write(rgb[y * row:(y + 1) * row].tobytes())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frame")
    ap.add_argument("out_prefix")
    ap.add_argument("--lib", default=os.environ.get("GDRECON_LIB",
                                                    os.path.join(ROOT, "target/release/libgdrecon.so")))
    args = ap.parse_args()
    lib = load(args.lib)
    v = lib.gdr_version()
    print(f"libgdrecon {v // 10000}.{v // 100 % 100}.{v % 100}")

    ctx = C.c_void_p()
    call(lib, "gdr_context_new", C.byref(ctx))
    call(lib, "gdr_context_set_int", ctx, b"threads", 0)
    call(lib, "gdr_context_commit", ctx)
    frame = C.c_void_p()
    call(lib, "gdr_frame_read", args.frame.encode(), C.byref(frame))
    w, h, spp = C.c_size_t(), C.c_size_t(), C.c_float()
    call(lib, "gdr_frame_get_info", frame, C.byref(w), C.byref(h), C.byref(spp))
    width, height = w.value, h.value
    print(f"{args.frame}: {width} x {height}, {spp.value:g} spp")

    out = array.array("f", bytes(4 * width * height * 3))
    out_ptr = out.buffer_info()[0]
    fractions = []
    progress = PROGRESS_FN(lambda user, fraction: fractions.append(fraction) is None)

    m = 0
    while (method := lib.gdr_method_name(m)) is not None:
        m += 1
        filt = C.c_void_p()
        call(lib, "gdr_filter_new", ctx, method, C.byref(filt))
        try:
            for layer in LAYERS:
                data, channels = C.POINTER(C.c_float)(), C.c_size_t()
                call(lib, "gdr_frame_get_layer", frame, layer.encode(), C.byref(data), C.byref(channels))
                if data:
                    call(lib, "gdr_filter_set_image_planar", filt, layer.encode(),
                         C.cast(data, C.c_void_p), width, height, channels.value, 0, 0)
            call(lib, "gdr_filter_set_image", filt, b"output", out_ptr, width, height, 3, 0, 0)
            call(lib, "gdr_filter_set_float", filt, b"spp", spp.value)
            call(lib, "gdr_filter_set_progress_callback", filt, progress, None)
            call(lib, "gdr_filter_commit", filt)
            fractions.clear()
            call(lib, "gdr_filter_execute", filt)
            report = C.c_char_p()
            call(lib, "gdr_filter_get_report", filt, C.byref(report))
            print(report.value.decode(), end="")
            print(f"  progress: {len(fractions)} updates, last {fractions[-1]:.2f}")
        finally:
            call(lib, "gdr_filter_release", C.byref(filt))
        path = f"{args.out_prefix}_{method.decode()}.pfm"
        write_pfm(path, out, width, height)
        print(f"wrote {path}")
    if not all(map(lambda x: x == x and abs(x) != float("inf"), out)):
        sys.exit("non-finite output")
    call(lib, "gdr_frame_release", C.byref(frame))
    call(lib, "gdr_context_release", C.byref(ctx))
    return 0


if __name__ == "__main__":
    sys.exit(main())
