//! This package's tests link libtorch (the actor MLP): give them an rpath to libtorch's lib dir so
//! they run without `LD_LIBRARY_PATH`. torch-sys publishes the dir as `DEP_TCH_LIBTORCH_LIB` (its
//! `links = "tch"` metadata) to packages that depend on it directly.
fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    match std::env::var("DEP_TCH_LIBTORCH_LIB") {
        Ok(dir) if !dir.is_empty() => println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}"),
        _ => println!(
            "cargo:warning=rfcl-policy: torch-sys did not say where libtorch is; tests will need LD_LIBRARY_PATH"
        ),
    }
}
