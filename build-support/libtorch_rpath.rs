// Included by the build.rs of every crate that links libtorch into a binary or a test
// executable. torch-sys' rpath is not inherited by downstream crates, and rustc's default
// `--as-needed` drops libtorch_cuda.so (CUDA then silently reports unavailable). Embedding the
// rpath and forcing the link makes the binaries run with an empty environment.
fn link_libtorch() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    if let Ok(lib_dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{lib_dir}");
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed");
        println!("cargo:rustc-link-arg=-ltorch");
    }
}
