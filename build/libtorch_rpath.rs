// Shared by the build scripts of the packages that link libtorch (`include!`d, so it is a plain
// function in each of them, not a crate).

/// Gives every target of the package an rpath to libtorch's lib dir, so that its binaries and
/// tests run without `LD_LIBRARY_PATH` (the venv's torch does not put its lib dir on the loader's
/// path). torch-sys publishes the dir as `DEP_TCH_LIBTORCH_LIB` (its `links = "tch"` metadata) to
/// packages that depend on it directly; without it, a warning names `package`.
fn libtorch_rpath(package: &str) {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    match std::env::var("DEP_TCH_LIBTORCH_LIB") {
        Ok(dir) if !dir.is_empty() => println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}"),
        _ => println!(
            "cargo:warning={package}: torch-sys did not say where libtorch is; \
             its binaries and tests will need LD_LIBRARY_PATH"
        ),
    }
}
