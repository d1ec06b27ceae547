include!("../build-support/libtorch_rpath.rs");

fn main() -> Result<(), Box<dyn std::error::Error>> {
    link_libtorch();
    // A protoc on PATH (or named by PROTOC) wins; otherwise use the vendored one, so a fresh
    // machine needs nothing installed by hand.
    if std::env::var_os("PROTOC").is_none() {
        let protoc = protoc_bin_vendored::protoc_bin_path()?;
        // SAFETY: build scripts are single-threaded at this point.
        unsafe { std::env::set_var("PROTOC", protoc) };
    }
    println!("cargo:rerun-if-changed=../proto/junction.proto");
    tonic_prost_build::configure()
        .codec_path("crate::grpc_codec::ContiguousCodec")
        .compile_protos(&["../proto/junction.proto"], &["../proto"])?;
    Ok(())
}
