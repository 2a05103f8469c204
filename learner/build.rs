//! Makes every target of this package (lib tests, integration tests, benches, the `learner` binary)
//! find libtorch at run time without `LD_LIBRARY_PATH`,
//! and keeps CUDA linked where the libtorch build has it (the linker drops it otherwise).
//!
//! * The libtorch lib dir comes from torch-sys's `links = "tch"` metadata (`DEP_TCH_LIBTORCH_LIB`),
//!   falling back to asking `$PYTHON_SYS_EXECUTABLE` where its torch lives.
//! * An rpath to that dir is emitted for every target (`cargo:rustc-link-arg`).
//! * `-ltorch_cuda` is forced past `--as-needed` only when `libtorch_cuda.so` is there **and** all of
//!   its own dependencies resolve (a CPU-only venv from `scripts/setup.sh` ships the file without the
//!   NVIDIA wheels; forcing it there would make every binary fail to start). `RFCL_LINK_CUDA=0|1`
//!   overrides the detection.
//! * `proto/tensorboard.proto` (the event-file subset of TensorFlow's protos, see
//!   `src/tensorboard.rs`) is compiled with protox + prost-build: no system protoc.
use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-changed=proto/tensorboard.proto");
    let fds = protox::compile(["tensorboard.proto"], ["proto"])
        .expect("compiling learner/proto/tensorboard.proto");
    prost_build::Config::new()
        .compile_fds(fds)
        .expect("generating the TensorBoard event messages");

    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    println!("cargo:rerun-if-env-changed=PYTHON_SYS_EXECUTABLE");
    println!("cargo:rerun-if-env-changed=RFCL_LINK_CUDA");
    let Some(lib_dir) = libtorch_lib_dir() else {
        println!(
            "cargo:warning=rfcl-learner: libtorch's lib dir not found; binaries will need LD_LIBRARY_PATH"
        );
        return;
    };
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib_dir.display());

    let cuda_lib = lib_dir.join("libtorch_cuda.so");
    let link_cuda = match std::env::var("RFCL_LINK_CUDA").as_deref() {
        Ok("1") => true,
        Ok("0") => false,
        _ => cuda_lib.exists() && all_dependencies_resolve(&cuda_lib),
    };
    if link_cuda {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed");
        println!("cargo:rustc-link-arg=-ltorch_cuda");
        println!("cargo:rustc-link-arg=-Wl,--as-needed");
    } else if cuda_lib.exists() {
        println!(
            "cargo:warning=rfcl-learner: {} has unresolved dependencies (CPU-only venv?): linking CPU-only",
            cuda_lib.display()
        );
    }
}

fn libtorch_lib_dir() -> Option<PathBuf> {
    if let Ok(dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") {
        let dir = PathBuf::from(dir);
        if dir.join("libtorch_cpu.so").exists() {
            return Some(dir);
        }
    }
    let python = std::env::var("PYTHON_SYS_EXECUTABLE").unwrap_or_else(|_| "python3".into());
    let out = Command::new(python)
        .args([
            "-c",
            "import torch, os; print(os.path.dirname(torch.__file__) + '/lib')",
        ])
        .output()
        .ok()?;
    let dir = PathBuf::from(String::from_utf8(out.stdout).ok()?.trim());
    dir.join("libtorch_cpu.so").exists().then_some(dir)
}

/// True when `ldd` finds every shared library `lib` needs (and `ldd` exists).
fn all_dependencies_resolve(lib: &Path) -> bool {
    match Command::new("ldd").arg(lib).output() {
        Ok(out) if out.status.success() => {
            !String::from_utf8_lossy(&out.stdout).contains("not found")
        }
        _ => false,
    }
}
