//! `actor render --out FILE`: the extension picks the format. MP4 and WebM go through the
//! `ffmpeg` on PATH (here a stand-in that records its arguments and keeps the raw frames it is
//! fed, so the test needs no encoder and checks exactly what the actor sends); without one a
//! GIF is written beside the requested file; an encoder that fails fails the render.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use junction_tests::{TempDir, bin};

const WIDTH: usize = 96;
const HEIGHT: usize = 64;
const STEPS: u64 = 6;

/// `actor render` of the autopilot for `STEPS` steps with `PATH=path`.
fn render(out: &Path, path: &str) -> Output {
    Command::new(bin("actor"))
        .args(["render", "--scenario", "intersection", "--steps"])
        .arg(STEPS.to_string())
        .arg("--size")
        .arg(format!("{WIDTH}x{HEIGHT}"))
        .arg("--out")
        .arg(out)
        .env("PATH", path)
        .output()
        .expect("actor render runs")
}

/// An executable `dir/ffmpeg` running `body` under /bin/sh.
fn fake_ffmpeg(dir: &Path, body: &str) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let program = dir.join("ffmpeg");
    std::fs::write(&program, format!("#!/bin/sh\n{body}\n")).unwrap();
    std::fs::set_permissions(&program, std::fs::Permissions::from_mode(0o755)).unwrap();
    program
}

fn report(output: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "render failed: {}\n{stdout}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

#[test]
fn video_formats_go_through_ffmpeg_and_fall_back_to_gif_without_it() {
    let dir = TempDir::new("render");

    // With an "ffmpeg": it is handed raw RGBA frames at 10 frames per second.
    let tools = dir.path().join("tools");
    let args_file = dir.path().join("ffmpeg-args");
    fake_ffmpeg(
        &tools,
        &format!(
            "printf '%s\\n' \"$@\" > {}\nfor last; do :; done\ncat > \"$last\"",
            args_file.display()
        ),
    );
    let path = format!("{}:/usr/bin:/bin", tools.display());
    for (name, codec) in [("replay.mp4", "libx264"), ("replay.webm", "libvpx-vp9")] {
        let out = dir.path().join(name);
        let json = report(&render(&out, &path));
        assert_eq!(json["out"], out.display().to_string());
        assert_eq!(json["format"], name.rsplit('.').next().unwrap());
        let frames = json["frames"].as_u64().unwrap() as usize;
        assert!(frames >= STEPS as usize, "{json}");
        let bytes = std::fs::metadata(&out).unwrap().len() as usize;
        assert_eq!(
            bytes,
            frames * WIDTH * HEIGHT * 4,
            "{name}: every frame, raw RGBA"
        );
        let args = std::fs::read_to_string(&args_file).unwrap();
        let args: Vec<&str> = args.lines().collect();
        for pair in [
            ["-f", "rawvideo"],
            ["-pix_fmt", "rgba"],
            ["-video_size", "96x64"],
            ["-framerate", "10"],
            ["-i", "pipe:0"],
            ["-c:v", codec],
        ] {
            assert!(
                args.windows(2).any(|w| w == pair),
                "{name}: ffmpeg not given {pair:?}: {args:?}"
            );
        }
    }

    // Without one: a GIF of the same name, and a warning that says what to install.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = dir.path().join("fallback.mp4");
    let output = render(&out, &empty.display().to_string());
    let json = report(&output);
    let gif = dir.path().join("fallback.gif");
    assert_eq!(
        (json["out"].as_str(), json["format"].as_str()),
        (Some(gif.display().to_string().as_str()), Some("gif"))
    );
    assert!(!out.exists(), "no MP4 without an encoder");
    assert_eq!(&std::fs::read(&gif).unwrap()[..6], b"GIF89a");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("ffmpeg not found on PATH: writing a GIF instead"),
        "{stderr}"
    );

    // An encoder that fails: the render fails with its message.
    let broken = dir.path().join("broken");
    fake_ffmpeg(&broken, "echo 'Unknown encoder libx264' >&2\nexit 1");
    let output = render(
        &dir.path().join("broken.mp4"),
        &format!("{}:/usr/bin:/bin", broken.display()),
    );
    assert!(
        !output.status.success(),
        "a failing ffmpeg must fail the render"
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("Unknown encoder libx264"), "{stderr}");

    // Other extensions are refused before anything is simulated.
    let output = render(&dir.path().join("replay.avi"), "/usr/bin:/bin");
    assert!(!output.status.success());
    assert!(
        String::from_utf8_lossy(&output.stderr).contains("must end in .gif, .mp4 or .webm"),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}
