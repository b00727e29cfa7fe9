//! `horizon-bake preview` on real files and pipes: a closed pipe exits quietly, and a contact
//! sheet of a large map has 512 px tiles with labels scaled to them. Regression tests from
//! tests/edges.rs (issue 25's sharp edges), each written to fail before its fix.

use crate::support::*;

/// `preview -o - | head -c 8`: the reader closes the pipe after 8 bytes; the CLI exits 0 and
/// prints nothing (a real pipe, from a real process; the PNG is far larger than a pipe buffer).
#[test]
fn preview_to_a_closed_pipe_exits_quietly() {
    use std::io::Read;
    use std::process::{Command, Stdio};
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, noise_png8(256, 256, 9)).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["preview", input.to_str().unwrap(), "-o", "-", "--shading", "none"])
        .args(["--size", "1024", "--radius", "2"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut head = [0u8; 8];
    let mut stdout = child.stdout.take().unwrap();
    stdout.read_exact(&mut head).unwrap();
    assert_eq!(&head, b"\x89PNG\r\n\x1a\n");
    drop(stdout);
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.is_empty(), "stderr: {err}");
    assert_eq!(out.status.code(), Some(0), "{:?}", out.status);
}

/// A contact sheet of a large map: tiles default to 512 px and labels scale with them (the CLI,
/// on a real file).
#[test]
fn contact_sheet_tiles_default_to_512_with_scaled_labels() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(1024, 768, 5)).unwrap();
    let out_png = dir.path().join("sheet.png");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["preview", input.to_str().unwrap(), "-o", out_png.to_str().unwrap()])
        .args(["--contact-sheet", "4", "--shading", "none"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&out_png).unwrap().to_rgba8();
    // 2×2 tiles of 512×384 with a 4 px gap, labels 8× the 7 px font plus two 4 px gaps.
    let (tw, th, gap, scale) = (512u32, 384u32, 4u32, 8u32);
    let label_h = 7 * scale + 2 * gap;
    assert_eq!(img.dimensions(), (gap + 2 * (tw + gap), gap + 2 * (th + label_h + gap)));
    // The first label ("AZ …°") is drawn with 8×8 px font pixels: its lit rows span 7·8 px.
    let (x0, y0) = (gap, gap + th + gap);
    let lit_rows: Vec<u32> = (y0..y0 + label_h)
        .filter(|&y| (x0..x0 + tw).any(|x| img.get_pixel(x, y).0[..3] == [240, 240, 240]))
        .collect();
    assert_eq!(lit_rows.len() as u32, 7 * scale, "{lit_rows:?}");
    assert_eq!(horizon_bake::preview::label_scale(40), 1);
}
