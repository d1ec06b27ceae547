//! The file `actor render` writes, chosen by the extension of `--out`: an animated GIF
//! (encoded here, always available), or MP4 (H.264) and WebM (VP9) through a system `ffmpeg`
//! fed raw RGBA frames on its standard input. Without `ffmpeg` on PATH, an MP4 or WebM
//! request writes a GIF beside it instead, with a warning, so a render never fails for want
//! of an encoder.

use std::ffi::OsString;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};

use anyhow::{Context, bail, ensure};

use crate::replay::GifWriter;
use junction_sim::render::Frame;

/// The encoder program looked up on PATH.
const FFMPEG: &str = "ffmpeg";

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VideoFormat {
    Gif,
    Mp4,
    Webm,
}

impl VideoFormat {
    /// The format `path`'s extension asks for (case-insensitive).
    pub fn of(path: &Path) -> anyhow::Result<VideoFormat> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("gif") => Ok(VideoFormat::Gif),
            Some("mp4") => Ok(VideoFormat::Mp4),
            Some("webm") => Ok(VideoFormat::Webm),
            _ => bail!(
                "--out {}: the file name must end in .gif, .mp4 or .webm (the format follows it)",
                path.display()
            ),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            VideoFormat::Gif => "gif",
            VideoFormat::Mp4 => "mp4",
            VideoFormat::Webm => "webm",
        }
    }

    /// ffmpeg's output options: widely playable H.264 and VP9 at a quality where the flat
    /// colours of the renderer stay clean.
    fn encoder_args(self) -> &'static [&'static str] {
        match self {
            VideoFormat::Gif => &[],
            VideoFormat::Mp4 => &[
                "-c:v",
                "libx264",
                "-pix_fmt",
                "yuv420p",
                "-crf",
                "23",
                "-movflags",
                "+faststart",
            ],
            VideoFormat::Webm => &[
                "-c:v",
                "libvpx-vp9",
                "-pix_fmt",
                "yuv420p",
                "-crf",
                "32",
                "-b:v",
                "0",
            ],
        }
    }
}

/// `name` as an executable file in one of the directories of `path` (a PATH value).
pub fn find_on_path(name: &str, path: Option<OsString>) -> Option<PathBuf> {
    use std::os::unix::fs::PermissionsExt;
    let path = path?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|candidate| {
            std::fs::metadata(candidate)
                .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        })
}

/// Frames per second for ffmpeg as an exact fraction of whole microseconds ("10" for 0.1 s,
/// "10/3" for 0.3 s): the decimal of an f32 reciprocal would drift.
fn frame_rate(frame_seconds: f32) -> String {
    const MICROS: u64 = 1_000_000;
    let micros = ((f64::from(frame_seconds) * MICROS as f64).round() as u64).max(1);
    let (mut a, mut b) = (MICROS, micros);
    while b != 0 {
        (a, b) = (b, a % b);
    }
    match (MICROS / a, micros / a) {
        (frames, 1) => frames.to_string(),
        (frames, seconds) => format!("{frames}/{seconds}"),
    }
}

/// Frames going into a GIF or an ffmpeg process.
pub enum VideoWriter {
    Gif(GifWriter),
    Ffmpeg(FfmpegWriter),
}

/// What was written: the file (a GIF beside the requested one when ffmpeg was missing) and
/// its format.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub path: PathBuf,
    pub format: VideoFormat,
}

impl VideoWriter {
    /// Opens `out` in the format its extension names; MP4 and WebM need `ffmpeg` on PATH,
    /// else the frames go to `out` with the extension `.gif`.
    pub fn create(
        out: &Path,
        width: usize,
        height: usize,
        frame_seconds: f32,
    ) -> anyhow::Result<(VideoWriter, Written)> {
        let format = VideoFormat::of(out)?;
        let ffmpeg = match format {
            VideoFormat::Gif => None,
            _ => {
                let found = find_on_path(FFMPEG, std::env::var_os("PATH"));
                if found.is_none() {
                    tracing::warn!(
                        requested = %out.display(),
                        "ffmpeg not found on PATH: writing a GIF instead (install ffmpeg, e.g. Debian's `ffmpeg` package, for {})",
                        format.name()
                    );
                }
                found
            }
        };
        match ffmpeg {
            Some(program) => {
                let writer =
                    FfmpegWriter::spawn(&program, out, format, width, height, frame_seconds)?;
                let written = Written {
                    path: out.to_path_buf(),
                    format,
                };
                Ok((VideoWriter::Ffmpeg(writer), written))
            }
            None => {
                let path = out.with_extension("gif");
                let writer = GifWriter::create(&path, width, height, frame_seconds)?;
                let written = Written {
                    path,
                    format: VideoFormat::Gif,
                };
                Ok((VideoWriter::Gif(writer), written))
            }
        }
    }

    pub fn write(&mut self, frame: &Frame) -> anyhow::Result<()> {
        match self {
            VideoWriter::Gif(gif) => gif.write(frame),
            VideoWriter::Ffmpeg(ffmpeg) => ffmpeg.write(frame),
        }
    }

    /// Completes the file: the GIF's trailer, or ffmpeg's end of input and its exit.
    pub fn finish(self) -> anyhow::Result<()> {
        match self {
            VideoWriter::Gif(gif) => gif.finish(),
            VideoWriter::Ffmpeg(ffmpeg) => ffmpeg.finish(),
        }
    }
}

/// An `ffmpeg` reading raw RGBA frames from its standard input.
pub struct FfmpegWriter {
    child: Child,
    stdin: Option<ChildStdin>,
    width: usize,
    height: usize,
    out: PathBuf,
}

impl FfmpegWriter {
    fn spawn(
        program: &Path,
        out: &Path,
        format: VideoFormat,
        width: usize,
        height: usize,
        frame_seconds: f32,
    ) -> anyhow::Result<FfmpegWriter> {
        ensure!(
            frame_seconds > 0.0 && frame_seconds.is_finite(),
            "frame duration {frame_seconds} s"
        );
        let mut command = Command::new(program);
        command
            .args(["-hide_banner", "-nostats", "-loglevel", "error", "-y"])
            .args(["-f", "rawvideo", "-pix_fmt", "rgba"])
            .arg("-video_size")
            .arg(format!("{width}x{height}"))
            .arg("-framerate")
            .arg(frame_rate(frame_seconds))
            .args(["-i", "pipe:0", "-an"])
            // yuv420p needs even sides: pad an odd frame by one pixel.
            .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
            .args(format.encoder_args())
            .arg(out)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            // Errors only (-loglevel error): small, read when it exits.
            .stderr(Stdio::piped());
        let mut child = command
            .spawn()
            .with_context(|| format!("starting {}", program.display()))?;
        let stdin = child.stdin.take();
        Ok(FfmpegWriter {
            child,
            stdin,
            width,
            height,
            out: out.to_path_buf(),
        })
    }

    fn write(&mut self, frame: &Frame) -> anyhow::Result<()> {
        ensure!(
            (frame.width(), frame.height()) == (self.width, self.height),
            "frame of {}×{} in a video of {}×{}",
            frame.width(),
            frame.height(),
            self.width,
            self.height
        );
        let Some(stdin) = self.stdin.as_mut() else {
            bail!("ffmpeg's input is closed");
        };
        if let Err(e) = stdin.write_all(frame.pixels()) {
            // ffmpeg stopped reading: its own message says why.
            self.stdin = None;
            let reason = self.stderr();
            let _ = self.child.wait();
            bail!("ffmpeg stopped taking frames ({e}): {reason}");
        }
        Ok(())
    }

    fn finish(mut self) -> anyhow::Result<()> {
        // Closing its input tells ffmpeg the video is complete.
        self.stdin = None;
        let status = self.child.wait().context("waiting for ffmpeg")?;
        if !status.success() {
            let reason = self.stderr();
            bail!(
                "ffmpeg failed ({status}) writing {}: {reason}",
                self.out.display()
            );
        }
        Ok(())
    }

    fn stderr(&mut self) -> String {
        let mut text = String::new();
        if let Some(mut stderr) = self.child.stderr.take() {
            let _ = stderr.read_to_string(&mut text);
        }
        text.trim().to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_extension_names_the_format() {
        assert_eq!(
            VideoFormat::of(Path::new("a/replay.gif")).unwrap(),
            VideoFormat::Gif
        );
        assert_eq!(
            VideoFormat::of(Path::new("replay.MP4")).unwrap(),
            VideoFormat::Mp4
        );
        assert_eq!(
            VideoFormat::of(Path::new("replay.webm")).unwrap(),
            VideoFormat::Webm
        );
        let error = VideoFormat::of(Path::new("replay.avi"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("must end in .gif, .mp4 or .webm"), "{error}");
        assert!(VideoFormat::of(Path::new("replay")).is_err());
    }

    #[test]
    fn frame_rates_are_exact_fractions() {
        assert_eq!(frame_rate(0.1), "10");
        assert_eq!(frame_rate(0.3), "10/3");
        assert_eq!(frame_rate(2.0), "1/2");
    }

    #[test]
    fn programs_are_found_on_path_only_when_executable() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("junction-video-{}", std::process::id()));
        let (empty, bin) = (dir.join("empty"), dir.join("bin"));
        std::fs::create_dir_all(&empty).unwrap();
        std::fs::create_dir_all(&bin).unwrap();
        let program = bin.join("ffmpeg");
        std::fs::write(&program, "#!/bin/sh\n").unwrap();
        let path = std::env::join_paths([&empty, &bin]).unwrap();
        assert_eq!(
            find_on_path("ffmpeg", Some(path.clone())),
            None,
            "not executable"
        );
        std::fs::set_permissions(&program, std::fs::Permissions::from_mode(0o755)).unwrap();
        assert_eq!(find_on_path("ffmpeg", Some(path)), Some(program));
        assert_eq!(find_on_path("ffmpeg", Some(empty.into_os_string())), None);
        assert_eq!(find_on_path("ffmpeg", None), None);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
