"""float32 C against the float64 step over whole protocol trials, and the step on a Cortex-M4 (issue 48.3).

    python benchmarks/float32_c.py MODEL [--trials 100] [--out results/float32/NAME.md] [--cortex-m]

For each input regime of the protocol's noisy table (``Protocol()``: seed 2026, 50 s, 0.1 process and
measurement noise; the trials come from the trial cache) the model's C main example is built twice by gcc
(``generate_c(math="libm")``, which is bitwise the CasADi VM, and ``generate_c(precision="float32")``), each
trial is fed to both, and the float32 estimates are compared with the float64 ones over every sample:
the largest absolute difference per state, that difference over the state's range in the trials, and the
SMAPE of both against the true states (the protocol's score; the accuracy that float32 changes).

With ``--cortex-m`` (needs ``arm-none-eabi-gcc`` with newlib and ``qemu-system-arm``: Debian's
``gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm``) the float32 step is also compiled for a
Cortex-M4F (``-mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2``), its flash and RAM sizes read with
``arm-none-eabi-size``, and it runs under QEMU's MPS2-AN386 board (a Cortex-M4) on the first trial's samples:
QEMU counts the instructions (``-icount shift=0``: the virtual clock advances 1 ns per instruction, read with
the SysTick timer at the board's 25 MHz), and the executed instructions, classed by the disassembly, give a
cycle estimate with the Cortex-M4's documented instruction timings (Arm's Cortex-M4 Technical Reference
Manual, section 3.3; zero-wait-state memory; QEMU itself is not cycle accurate). The estimates computed on
the emulated core are compared with the float32 ones of the host.

``--out`` is refused before any work where it exists, and written whole or not at all (never over a file).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from kklcasadi import metrics, provenance
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.model.shipped import resolve
from kklcasadi.observer.codegen import generate_c
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant import signals
from kklcasadi.writes import refuse_existing, write_file

GCC = ("gcc", "-std=c99", "-O2")
#: The regime whose first trial runs on the emulated core.
ARM_REGIME = "sinusoid"
ARM = ("arm-none-eabi-gcc", "-std=c99", "-O2", "-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16",
       "-mfloat-abi=hard", "-ffunction-sections", "-fdata-sections")
#: Cortex-M4 cycles per instruction class (TRM 3.3, processor instruction timings, and the FPU's, 7.2.3):
#: loads and stores 2 (a load after a load pipelines to 1: counted 2, an upper bound), branches taken 1 + 2
#: (pipeline refill), VFP single-precision add/mul 1, multiply-accumulate 3, divide and square root 14,
#: load/store multiple 1 + registers.
CYCLES = {"alu": 1, "mul": 1, "div": 7, "load": 2, "store": 2, "branch": 3, "vadd": 1, "vmul": 1, "vmla": 3,
          "vdiv": 14, "vsqrt": 14, "vmov": 1, "vcvt": 1, "vcmp": 1, "vldr": 2, "vstr": 2}


def build(obs, folder: Path, name: str, **options) -> Path:
    files = generate_c(obs, folder, name, **options)
    binary = folder / name
    subprocess.run([*GCC, str(files[0]), str(files[2]), "-lm", "-o", str(binary)], check=True)
    return binary


def run(binary: Path, t: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One trial through the main example: its CSV in (``time,y1..,u1..``), the states' columns of its output
    (``time,<states>[,in_domain],status``); exit status 3 (samples the guard held) gives estimates all the same."""
    header = ",".join(["time", *(f"y{i + 1}" for i in range(y.shape[1])), *(f"u{i + 1}" for i in range(u.shape[1]))])
    text = header + "\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in np.column_stack([t, y, u]))
    done = subprocess.run([str(binary)], input=text, capture_output=True, text=True)
    if done.returncode not in (0, 3):
        raise RuntimeError(f"{binary.name}: exit status {done.returncode}: {done.stderr.strip()}")
    lines = done.stdout.splitlines()
    states = [i for i, name in enumerate(lines[0].split(",")) if name not in ("time", "in_domain", "status")]
    return np.loadtxt(lines[1:], delimiter=",", ndmin=2)[:, states]


# ----------------------------------------------------------------------------- Cortex-M4 under QEMU
HARNESS = r"""
#include <stdint.h>
#include <string.h>
#include "NAME.h"
#include "samples.h"
#define SYST_CSR (*(volatile uint32_t*) 0xE000E010)
#define SYST_RVR (*(volatile uint32_t*) 0xE000E014)
#define SYST_CVR (*(volatile uint32_t*) 0xE000E018)
#define CPACR (*(volatile uint32_t*) 0xE000ED88)
extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
static casadi_real z[MACRO_NZ], z_next[MACRO_NZ], win[MACRO_NW], win_next[MACRO_NW], xhat[MACRO_NX];
static const casadi_real* arg[MACRO_SZ_ARG];
static casadi_real* res[MACRO_SZ_RES];
static casadi_int iw[MACRO_SZ_IW + 1];
static casadi_real work[MACRO_SZ_W + 1];
static void semihost(int op, void* a) {
  register int r0 __asm__("r0") = op;
  register void* r1 __asm__("r1") = a;
  __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
}
static void put(const char* s) { semihost(0x04, (void*) s); }
static void put_u(uint64_t v) {
  char b[24]; int i = 23; b[i] = 0;
  do { b[--i] = '0' + v % 10; v /= 10; } while (v);
  put(b + i);
}
static void put_hex(uint32_t v) {
  char b[9]; int i;
  for (i = 7; i >= 0; i--, v >>= 4) b[i] = "0123456789abcdef"[v & 15];
  b[8] = 0; put(b);
}
int main(void) {
  int k, i;
  uint64_t ticks = 0;
  uint32_t t0, t1, bits;
  for (i = 0; i < MACRO_NZ; i++) z[i] = 0;
  arg[0] = Y[0]; arg[1] = U[0]; res[0] = win; NAME_init(arg, res, iw, work, 0);
  arg[0] = z; arg[1] = win; res[0] = xhat; NAME_decode(arg, res, iw, work, 0);
  SYST_RVR = 0xFFFFFF; SYST_CVR = 0; SYST_CSR = 5;           /* processor clock, no interrupt */
  for (k = 1; k < NSAMPLES; k++) {
    arg[0] = z; arg[1] = win; arg[2] = Y[k - 1]; arg[3] = Y[k]; arg[4] = U[k];
    res[0] = z_next; res[1] = win_next; res[2] = xhat;
    t0 = SYST_CVR;
    NAME_step(arg, res, iw, work, 0);
    t1 = SYST_CVR;
    ticks += (t0 - t1) & 0xFFFFFF;
    memcpy(z, z_next, sizeof z); memcpy(win, win_next, sizeof win);
    put("x"); for (i = 0; i < MACRO_NX; i++) { memcpy(&bits, &xhat[i], 4); put(" "); put_hex(bits); } put("\n");
  }
  put("ticks "); put_u(ticks); put("\n");
  return 0;
}
void Reset_Handler(void) {
  uint32_t *src = &_sidata, *dst = &_sdata;
  while (dst < &_edata) *dst++ = *src++;
  for (dst = &_sbss; dst < &_ebss;) *dst++ = 0;
  CPACR |= 0xFu << 20;                                        /* the FPU */
  __asm__ volatile("dsb\n isb");
  main();
  semihost(0x18, (void*) 0x20026);                            /* exit */
  for (;;) {}
}
static void Fault_Handler(void) { put("fault\n"); semihost(0x18, (void*) 0x20023); for (;;) {} }
__attribute__((section(".isr_vector"), used)) static void (*const vectors[16])(void) = {
  (void (*)(void)) &_estack, Reset_Handler, Fault_Handler, Fault_Handler, Fault_Handler, Fault_Handler,
  Fault_Handler};
void* _sbrk(int n) { (void) n; return (void*) -1; }
"""
LINKER = """MEMORY { FLASH (rx) : ORIGIN = 0x00000000, LENGTH = 4M  RAM (rwx) : ORIGIN = 0x20000000, LENGTH = 4M }
_estack = ORIGIN(RAM) + LENGTH(RAM);
SECTIONS {
  .text : { KEEP(*(.isr_vector)) *(.text*) *(.rodata*) . = ALIGN(4); } > FLASH
  .ARM.exidx : { *(.ARM.exidx*) } > FLASH
  _sidata = LOADADDR(.data);
  .data : { _sdata = .; *(.data*) . = ALIGN(4); _edata = .; } > RAM AT > FLASH
  .bss : { _sbss = .; *(.bss*) *(COMMON) . = ALIGN(4); _ebss = .; } > RAM
}
"""


def _klass(mnemonic: str) -> str:
    m = mnemonic.split(".")[0]
    if m.startswith(("vldr", "vldm", "vpop")):
        return "vldr"
    if m.startswith(("vstr", "vstm", "vpush")):
        return "vstr"
    if m.startswith(("vmla", "vmls", "vfma", "vfms", "vnmla", "vnmls", "vfnma", "vfnms")):
        return "vmla"
    for key in ("vdiv", "vsqrt", "vcvt", "vcmp"):
        if m.startswith(key):
            return key
    if m.startswith(("vadd", "vsub", "vabs", "vneg")):
        return "vadd"
    if m.startswith(("vmul", "vnmul")):
        return "vmul"
    if m.startswith(("vmov", "vmrs", "vmsr", "vsel", "vmax", "vmin")):
        return "vmov"
    if m.startswith(("ldr", "ldm", "pop")):
        return "load"
    if m.startswith(("str", "stm", "push")):
        return "store"
    if m.startswith(("b", "cb")) and not m.startswith(("bic", "bfi", "bfc")):
        return "branch"
    if m.startswith(("mul", "mla", "mls", "smul", "umul", "smla", "umla")):
        return "mul"
    if m.startswith(("sdiv", "udiv")):
        return "div"
    return "alu"


def cortex_m(obs, folder: Path, t: np.ndarray, y: np.ndarray, u: np.ndarray, steps: int) -> dict:
    """Build the float32 step for a Cortex-M4F and run ``steps`` steps under QEMU; sizes, instructions, cycles."""
    name = "obs32"
    files = generate_c(obs, folder, name, precision="float32", overwrite=True)
    n = steps + 1
    rows = lambda a: ",\n".join("{" + ", ".join(f"{float(v)!r}f" for v in r) + "}" for r in a)  # noqa: E731
    (folder / "samples.h").write_text(f"#define NSAMPLES {n}\nstatic const casadi_real Y[{n}][{obs.ny}] = {{\n"
                                      f"{rows(y[:n])}}};\nstatic const casadi_real U[{n}][{obs.nu}] = {{\n"
                                      f"{rows(u[:n])}}};\n")
    (folder / "harness.c").write_text(HARNESS.replace("NAME", name).replace("MACRO", name.upper()))
    (folder / "link.ld").write_text(LINKER)
    elf = folder / "obs32.elf"
    subprocess.run([*ARM, "-nostartfiles", f"-T{folder / 'link.ld'}", "-Wl,--gc-sections", f"-I{folder}",
                    str(files[0]), str(folder / "harness.c"), "-lm", "-lc", "-lgcc", "-o", str(elf)], check=True)
    size = subprocess.run(["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True, check=True).stdout
    sections = {m.group(1): int(m.group(2)) for m in re.finditer(r"^\.(\w+)\s+(\d+)", size, re.MULTILINE)}
    qemu = ["qemu-system-arm", "-M", "mps2-an386", "-nographic", "-semihosting", "-icount", "shift=0",
            "-kernel", str(elf)]
    wall = time.perf_counter()
    done = subprocess.run(qemu, capture_output=True, text=True, timeout=3600)
    out = done.stdout + done.stderr                              # semihosting writes to either, by version
    wall = time.perf_counter() - wall
    ticks = int(re.search(r"^ticks (\d+)", out, re.MULTILINE).group(1))
    xs = np.array([[np.frombuffer(bytes.fromhex(h), ">f4")[0] for h in line.split()[1:]]
                   for line in out.splitlines() if line.startswith("x ")], dtype=float)
    # the dynamic mix: QEMU's log of every executed translation block (one instruction each), steps 1..3
    mix_steps = 1
    (folder / "samples.h").write_text(re.sub(r"NSAMPLES \d+", f"NSAMPLES {mix_steps + 1}",
                                             (folder / "samples.h").read_text()))
    elf_mix = folder / "obs32_mix.elf"
    subprocess.run([*ARM, "-nostartfiles", f"-T{folder / 'link.ld'}", "-Wl,--gc-sections", f"-I{folder}",
                    str(files[0]), str(folder / "harness.c"), "-lm", "-lc", "-lgcc", "-o", str(elf_mix)], check=True)
    log = folder / "exec.log"
    subprocess.run([*qemu[:-1], str(elf_mix), "-singlestep", "-d", "exec,nochain", "-D", str(log)],
                   capture_output=True, text=True, timeout=3600)
    disassembly = subprocess.run(["arm-none-eabi-objdump", "-d", str(elf_mix)], capture_output=True, text=True,
                                 check=True).stdout
    mnemonics = {int(m.group(1), 16): m.group(2) for m in
                 re.finditer(r"^\s*([0-9a-f]+):\s+(?:[0-9a-f]{4}\s?){1,2}\s+([a-z][\w.]*)", disassembly, re.MULTILINE)}
    symbols = sorted((int(m.group(1), 16), m.group(2)) for m in
                     re.finditer(r"^([0-9a-f]{8}) <([^>]+)>:", disassembly, re.MULTILINE))
    step_start = next(a for a, s in symbols if s == f"{name}_step")
    pcs = [int(m.group(1), 16) for m in re.finditer(r"Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/", log.read_text())]
    mix = Counter(_klass(mnemonics.get(pc, "alu")) for pc in pcs)
    total = sum(mix.values())
    cpi = sum(CYCLES[k] * v for k, v in mix.items()) / total
    return {"flash": sections.get("text", 0) + sections.get("data", 0), "ram": sections.get("data", 0)
            + sections.get("bss", 0), "instructions_per_step": ticks * 40 / steps, "steps": steps, "cpi": cpi,
            "mix": {k: v / total for k, v in mix.most_common()}, "xhat": xs, "qemu_wall": wall,
            "step_symbol": hex(step_start)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a model directory or a shipped model SYSTEM/METHOD")
    parser.add_argument("--trials", type=int, default=100, help="trials per input regime (default 100)")
    parser.add_argument("--out", help="the Markdown report to write (default: print it)")
    parser.add_argument("--cortex-m", action="store_true", help="also run the float32 step on a Cortex-M4 (QEMU)")
    parser.add_argument("--steps", type=int, default=200, help="--cortex-m: steps run on the emulated core")
    args = parser.parse_args()
    if args.out:
        refuse_existing({args.out: "--out"})
    obs = load_observer(resolve(args.model))
    protocol = Protocol(n_trials=args.trials)
    cache = TrialCache.default()
    lines = [f"float32 C against the float64 step, `{args.model}`. Protocol: the noisy table (seed {protocol.seed}, "
             f"{protocol.T:g} s, process and measurement noise {protocol.process_std:g}), {args.trials} trials per "
             "input regime; float64 is the C library build "
             "(`math=\"libm\"`, bitwise the CasADi VM), float32 `precision=\"float32\"`, both `gcc -std=c99 -O2`.",
             "", "| regime | max abs diff per state | max diff / state range | SMAPE float64 | SMAPE float32 |",
             "|---|---|---|---|---|"]
    worst = np.zeros(obs.nx)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        f64 = build(obs, folder / "f64", "obs64", math="libm")
        f32 = build(obs, folder / "f32", "obs32", precision="float32")
        first: tuple = ()
        for kind in signals.BENCHMARK_KINDS:
            batch = cache.trials(obs.system, protocol.cell(kind))
            ok = np.flatnonzero(batch.ok)
            x64 = np.stack([run(f64, batch.t, batch.y[i], batch.u[i]) for i in ok])
            x32 = np.stack([run(f32, batch.t, batch.y[i], batch.u[i]) for i in ok])
            if kind == ARM_REGIME:
                first = (batch.t, batch.y[ok[0]], batch.u[ok[0]], x32[0])
            diff = np.abs(x32 - x64).max(axis=(0, 1))
            span = np.ptp(batch.x[ok], axis=(0, 1))
            worst = np.maximum(worst, diff / span)
            s64, s32 = (float(np.mean(metrics.smape(batch.x[ok], x))) for x in (x64, x32))
            lines.append(f"| {kind} | {', '.join(f'{d:.2e}' for d in diff)} | "
                         f"{', '.join(f'{d:.2e}' for d in diff / span)} | {s64:.4f} | {s32:.4f} |")
            print(lines[-1], flush=True)
        lines += ["", f"Largest difference over a state's range: {worst.max():.2e}."]
        if args.cortex_m:
            missing = [tool for tool in ("arm-none-eabi-gcc", "qemu-system-arm") if shutil.which(tool) is None]
            if missing:
                raise SystemExit(f"--cortex-m: {', '.join(missing)} not found; install gcc-arm-none-eabi "
                                 "libnewlib-arm-none-eabi qemu-system-arm")
            t, y, u, host = first
            m = cortex_m(obs, folder / "arm", t, y, u, args.steps)
            agree = np.abs(m["xhat"] - host[1:m["steps"] + 1]).max()
            cycles = m["instructions_per_step"] * m["cpi"]
            lines += ["", f"On a Cortex-M4F (QEMU MPS2-AN386), `{' '.join(ARM)}`: flash {m['flash']} bytes (code and "
                      f"constants), RAM {m['ram']} bytes (static work arrays; no heap).",
                      "", f"- instructions per step: {m['instructions_per_step']:.0f} (QEMU `-icount shift=0`, "
                      f"{m['steps']} steps of the first trial of the '{ARM_REGIME}' regime)",
                      "- instruction mix (executed, the first step and the start): "
                      + ", ".join(f"{k} {v:.1%}" for k, v in m["mix"].items()),
                      f"- cycles per instruction from the mix and the Cortex-M4's timings: {m['cpi']:.2f}",
                      f"- cycle estimate per step: {cycles:.0f}, i.e. {cycles / 168:.0f} us at 168 MHz "
                      f"(STM32F4) and {cycles / 80:.0f} us at 80 MHz, with zero-wait-state memory "
                      "(flash wait states and caches add to it)",
                      f"- the emulated core's estimates against the host's float32 ones: max abs difference "
                      f"{agree:.2e}"]
    stamp = provenance.stamp(seeds={"protocol": protocol.seed}, note="benchmarks/float32_c.py")
    text = "\n".join(lines) + "\n"
    if args.out:
        write_file(args.out, provenance.markdown(text, stamp), argument="--out")
        print(f"wrote {args.out}")
    else:
        print(text)


if __name__ == "__main__":
    main()
