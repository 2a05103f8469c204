//! The `actor` binary and this package's tests link libtorch (the policy network, through
//! rfcl-policy): they get an rpath to libtorch's lib dir.
//!
//! `rfcl-sim-worker` embeds the Python of `PYO3_PYTHON` (the venv's): it gets an rpath to that
//! Python's own libpython (without it the loader takes Debian's libpython3.11, a different
//! build), and the venv's site-packages directory is recorded as `RFCL_PYTHON_SITE_PACKAGES` for
//! the worker to put on `sys.path`.
use std::process::Command;

include!("../build/libtorch_rpath.rs");

fn main() {
    libtorch_rpath("rfcl-actor");
    python_paths();
}

fn python_paths() {
    println!("cargo:rerun-if-env-changed=PYO3_PYTHON");
    let python = std::env::var("PYO3_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = "import sysconfig; print(sysconfig.get_config_var('LIBDIR') or ''); \
                  print(sysconfig.get_paths()['purelib'])";
    let out = Command::new(&python).args(["-c", script]).output();
    let text = match out {
        Ok(o) if o.status.success() => String::from_utf8_lossy(&o.stdout).into_owned(),
        _ => {
            println!(
                "cargo:warning=rfcl-actor: could not ask {python} for its library and site-packages \
                 directories; set PYO3_PYTHON to the venv's python (scripts/setup.sh does)"
            );
            return;
        }
    };
    let mut lines = text.lines();
    if let Some(libdir) = lines.next().filter(|l| !l.is_empty()) {
        println!("cargo:rustc-link-arg-bin=rfcl-sim-worker=-Wl,-rpath,{libdir}");
    }
    if let Some(site) = lines.next().filter(|l| !l.is_empty()) {
        println!("cargo:rustc-env=RFCL_PYTHON_SITE_PACKAGES={site}");
    }
}
