"""A CPU harness for the CUDA branches of the warp helpers (``kernels/rasterize_warp.py``).

The helpers' ``coop`` code runs only in a CUDA build, where a warp's 32 lanes exchange values with shuffles and
votes; CI has no GPU. This module compiles the helpers' own native snippets, unchanged, as C++ with
``__CUDA_ARCH__`` defined and the CUDA intrinsics they use emulated: each lane is a thread, a shuffle or a vote
writes the lane's value to a table, waits at a barrier for the warp, and reads its partner's; ``__shared__`` is
one static buffer for the warp's threads; atomics take a lock. Warp's array and vector types are stood in for by
minimal ones with the same names and members. The driver (C++ the test writes) runs one warp, prints the results
and the test compares them with NumPy.

``compile_helpers`` returns the C++ source of the snippets as functions of the given signatures, for float32 and
float64; ``build`` compiles it with a driver into an executable (g++, C++20).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

SHIMS = r"""
#include <atomic>
#include <barrier>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <thread>
#include <vector>

#define __CUDA_ARCH__ 900
#define __shared__ static
#define __align__(n) __attribute__((aligned(n)))
#define CUDA_CALLABLE

namespace wp {
typedef float float32;
typedef double float64;
typedef int32_t int32;
typedef uint64_t uint64;
template <unsigned L, class T> struct vec_t {
    T c[L];
    vec_t() : c{} {}
    template <class... A> vec_t(A... a) : c{T(a)...} {}
    T& operator[](int i) { return c[i]; }
    const T& operator[](int i) const { return c[i]; }
};
template <unsigned L, class T> vec_t<L, T> operator+(vec_t<L, T> a, const vec_t<L, T>& b) {
    for (unsigned k = 0; k < L; ++k) a.c[k] += b.c[k];
    return a;
}
typedef vec_t<4, float> vec4;
typedef vec_t<4, double> vec4d;
template <class T> struct array_t {
    T* data;
    int shape[4];
    int strides[4];
};
template <class T> T* address(const array_t<T>& a, int i) { return (T*)((char*)a.data + i * a.strides[0]); }
template <class T> T* address(const array_t<T>& a, int i, int j) {
    return (T*)((char*)a.data + i * a.strides[0] + j * a.strides[1]);
}
template <class T> T& index(const array_t<T>& a, int i) { return *address(a, i); }
template <class T> T& index(const array_t<T>& a, int i, int j) { return *address(a, i, j); }
static std::mutex atomic_lock;
template <class T> void atomic_add(const array_t<T>& a, int i, int j, T v) {
    std::lock_guard<std::mutex> g(atomic_lock);
    *address(a, i, j) = *address(a, i, j) + v;
}
}  // namespace wp

struct int4 { int x, y, z, w; };
struct float4 { float x, y, z, w; };
struct double2 { double x, y; };
struct dim3 { unsigned x; };
static thread_local dim3 threadIdx;
static dim3 blockDim = {256};
static std::barrier<>* warp_barrier;
static unsigned char exchange[32][8];

template <class T> T __ldg(const T* p) { return *p; }
void __syncwarp() { warp_barrier->arrive_and_wait(); }
template <class T> T __shfl_xor_sync(unsigned, T v, int o) {
    const unsigned lane = threadIdx.x & 31;
    std::memcpy(exchange[lane], &v, sizeof(T));
    warp_barrier->arrive_and_wait();
    T r;
    std::memcpy(&r, exchange[lane ^ o], sizeof(T));
    warp_barrier->arrive_and_wait();
    return r;
}
unsigned __ballot_sync(unsigned, bool b) {
    const unsigned lane = threadIdx.x & 31;
    exchange[lane][0] = b;
    warp_barrier->arrive_and_wait();
    unsigned bits = 0;
    for (int l = 0; l < 32; ++l) bits |= unsigned(exchange[l][0] != 0) << l;
    warp_barrier->arrive_and_wait();
    return bits;
}
int __popc(unsigned x) { return __builtin_popcount(x); }
#define __builtin_assume(x) ((void)0)
#define __isShared(p) true
[[noreturn]] void __trap() { std::abort(); }
template <class T> void atomicAdd(T* p, T v) {
    std::lock_guard<std::mutex> g(wp::atomic_lock);
    *p = *p + v;
}

// one warp: lane l runs f(l) on its own thread as threadIdx.x = 32 * warp + l
template <class Fn> void run_warp(int warp, Fn f) {
    std::barrier<> bar(32);
    warp_barrier = &bar;
    std::vector<std::thread> lanes;
    for (int l = 0; l < 32; ++l)
        lanes.emplace_back([&, l] { threadIdx.x = 32 * warp + l; f(l); });
    for (auto& t : lanes) t.join();
}
template <class T> wp::array_t<T> view(T* p, int rows, int cols) {
    wp::array_t<T> a{};
    a.data = p;
    a.shape[0] = rows;
    a.shape[1] = cols;
    a.strides[0] = int(sizeof(T)) * cols;
    a.strides[1] = int(sizeof(T));
    return a;
}
"""


def function_source(name: str, snippet: str, ret: str, params: list[tuple[str, str]]) -> str:
    """A C++ function ``name`` with ``params`` ([(type, name)]) whose body is a helper's native snippet."""
    args = ", ".join(f"{t} {n}" for t, n in params)
    return f"static {ret} {name}({args})\n{{\n{snippet}\n}}\n"


def build(source: str, out: Path) -> Path | None:
    """Compile ``source`` (shims, helpers and a ``main``) into ``out``; None without g++ (the test then skips)."""
    gxx = shutil.which("g++")
    if gxx is None:
        return None
    src = out.with_suffix(".cpp")
    src.write_text(source)
    res = subprocess.run([gxx, "-std=c++20", "-O1", "-pthread", "-w", "-o", str(out), str(src)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise AssertionError(f"the helpers did not compile as C++:\n{res.stderr[-4000:]}")
    return out
