"""Lab (#59): a poor man's sampler for a peer's train.py on the device.

python3 lab/device/stack_sample.py OUT_STACKS SECONDS_BETWEEN -- SCRIPT ARGS...  runs SCRIPT as __main__ with
faulthandler dumping every thread's stack to OUT_STACKS every SECONDS_BETWEEN s (no profiler overhead);
python3 lab/device/stack_sample.py --summary OUT_STACKS prints the most frequent innermost frames.
"""
import collections
import re
import runpy
import sys
import threading
import time
import traceback


def short(f: tuple[str, str, str]) -> str:
    return f"{f[0].split('/')[-1]}:{f[1]} {f[2]}"


if sys.argv[1] == "--summary":
    with open(sys.argv[2], errors="replace") as fh:
        text = fh.read()
    blocks = re.split(r"\n(?=Thread 0x|Current thread 0x)", text)
    leaf, top3 = collections.Counter(), collections.Counter()
    for b in blocks:
        frames = re.findall(r'File "([^"]+)", line (\d+) in (\S+)', b)
        if not frames or "threading.py" in frames[-1][0] and len(frames) < 4:
            continue
        ours = [f for f in frames if "pgsr_dpsr" in f[0] or "peers/" in f[0]]
        leaf[short(frames[0])] += 1
        top3[" <- ".join(short(f) for f in ours[:3])] += 1
    print(len(blocks), "stacks")
    for name, c in [("innermost frames", leaf), ("innermost frames in the peer's code", top3)]:
        print("==", name)
        for k, v in c.most_common(25):
            print(f"{v:5d}  {k}")
    sys.exit(0)
out, every = sys.argv[1], float(sys.argv[2])
assert sys.argv[3] == "--"
main_id = threading.main_thread().ident


def sample() -> None:
    # holds the GIL while it reads the main thread's frames (faulthandler's watchdog does not, and crashed train.py)
    with open(out, "w") as f:
        while True:
            time.sleep(every)
            frame = sys._current_frames().get(main_id)
            if frame is None:
                continue
            f.write("Thread 0x0 (most recent call first):\n")
            for fs in reversed(traceback.extract_stack(frame)):
                f.write(f'  File "{fs.filename}", line {fs.lineno} in {fs.name}\n')
            f.flush()


threading.Thread(target=sample, daemon=True).start()
sys.argv = sys.argv[4:]
runpy.run_path(sys.argv[0], run_name="__main__")
