//! `pma render` end to end: dataset views with a model trained by `pma train`, retargeted
//! AIST++ motion from `pma convert motion` on an orbit, bullet time, and clear errors.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::run::{
    aist_motion, fails_with, ok, pma, read_json, read_motion, s, tiny_scene, trained_scene,
    untrained_tiny,
};
use image::AnimationDecoder;

/// 12 frames of the embedded AIST++ dance at 15 fps.
fn motion(dir: &Path) -> PathBuf {
    aist_motion(&dir.join("dance.npz"), &["--frames", "0:48", "--fps", "15"])
}

fn png_size(path: &Path) -> (u32, u32) {
    image::image_dimensions(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn gif_frames(path: &Path) -> Vec<image::Frame> {
    let f = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    image::codecs::gif::GifDecoder::new(f)
        .unwrap()
        .into_frames()
        .collect_frames()
        .unwrap()
}

/// `pma render --model MODEL EXTRA... --out OUT --quiet`.
fn render(model: &Path, out: &Path, extra: &[&str]) -> Output {
    pma(&[
        &["render", "--model", s(model)],
        extra,
        &["--out", s(out), "--quiet"],
    ]
    .concat())
}

fn report(dir: &Path) -> serde_json::Value {
    read_json(&dir.join("render.json"))
}

#[test]
fn dataset_views_of_a_trained_model() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, model) = trained_scene(tmp.path(), 1, "2");
    let out = tmp.path().join("views");
    let stdout = ok(render(
        &model,
        &out,
        &[
            "--data",
            s(&scene),
            "--split",
            "novel_view",
            "--frames",
            "0:2",
        ],
    ))
    .stdout;
    assert!(String::from_utf8_lossy(&stdout).contains("rendered 2 frame(s) of 24x24"));
    for k in 0..2 {
        assert_eq!(png_size(&out.join(format!("frame_{k:04}.png"))), (24, 24));
    }
    assert!(!out.join("frame_0002.png").exists());
    let frames = gif_frames(&out.join("render.gif"));
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[0].buffer().dimensions(), (24, 24));
    let rep = report(&out);
    assert_eq!(rep["camera"], "dataset");
    assert_eq!(rep["view_dirs"], "normalized");
    assert_eq!(rep["frames"].as_array().unwrap().len(), 2);
    assert!(rep["seconds_per_frame"].as_f64().unwrap() > 0.0);
    // Only the outputs are left in the directory (no temporary files).
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "frame_0000.png",
            "frame_0001.png",
            "render.gif",
            "render.json"
        ]
    );
}

#[test]
fn retargeted_dance_on_an_orbit_at_a_chosen_size() {
    let tmp = tempfile::tempdir().unwrap();
    let model = untrained_tiny(tmp.path());
    let dance = motion(tmp.path());
    let out = tmp.path().join("orbit");
    ok(render(
        &model,
        &out,
        &[
            "--poses",
            s(&dance),
            "--res",
            "32x20",
            "--frames",
            "2:6",
            "--views",
            "4",
            "--background",
            "white",
            "--strip",
            "2",
        ],
    ));
    for k in 0..4 {
        assert_eq!(png_size(&out.join(format!("frame_{k:04}.png"))), (32, 20));
    }
    assert_eq!(png_size(&out.join("strip.png")), (64, 20));
    assert_eq!(gif_frames(&out.join("render.gif")).len(), 4);
    let rep = report(&out);
    assert_eq!(rep["camera"], "orbit");
    // The motion was converted on the same rest pose as the avatar's: legs are equal.
    assert!((rep["root_scale"].as_f64().unwrap() - 1.0).abs() < 1e-9);
    let frames = rep["frames"].as_array().unwrap();
    assert_eq!(frames[0]["pose"], "motion frame 2");
    assert_eq!(frames[3]["pose"], "motion frame 5");
    // Four views per turn: the cameras are a quarter turn apart around the body.
    let origin = |k: usize| -> Vec<f64> {
        frames[k]["camera_origin"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect()
    };
    let (a, c) = (origin(0), origin(2));
    assert!((a[1] - c[1]).abs() < 0.05, "same height: {a:?} {c:?}");
    // Opposite sides of the dancer, who barely moves between frames 2 and 4.
    let ds = read_motion(&dance);
    let root = ds.root_locs.as_ref().unwrap().row(2).to_vec();
    let mid = [(a[0] + c[0]) / 2.0, (a[2] + c[2]) / 2.0];
    assert!(
        (mid[0] - root[0] as f64).abs() < 0.2 && (mid[1] - root[2] as f64).abs() < 0.2,
        "cameras {a:?} {c:?} are not centred on the root {root:?}"
    );
    let gap = ((a[0] - c[0]).powi(2) + (a[2] - c[2]).powi(2)).sqrt();
    assert!(gap > 2.0, "{gap}");
    // White background where nothing was traced: the image corner.
    let img = image::open(out.join("frame_0000.png")).unwrap().to_rgb8();
    assert_eq!(img.get_pixel(0, 0).0, [255, 255, 255]);
}

#[test]
fn follow_camera_moves_with_the_root_only() {
    let tmp = tempfile::tempdir().unwrap();
    let model = untrained_tiny(tmp.path());
    let dance = motion(tmp.path());
    let out = tmp.path().join("follow");
    ok(render(
        &model,
        &out,
        &[
            "--poses",
            s(&dance),
            "--camera",
            "follow",
            "--res",
            "16x16",
            "--frames",
            "0:12",
            "--no-gif",
        ],
    ));
    let rep = report(&out);
    assert_eq!(rep["camera"], "follow");
    let ds = read_motion(&dance);
    let roots = ds.root_locs.unwrap();
    let frames = rep["frames"].as_array().unwrap();
    let o = |k: usize, c: usize| frames[k]["camera_origin"][c].as_f64().unwrap();
    for k in [5, 11] {
        for c in [0, 2] {
            let moved = o(k, c) - o(0, c);
            let body = (roots[[k, c]] - roots[[0, c]]) as f64;
            assert!(
                (moved - body).abs() < 1e-4,
                "frame {k} axis {c}: {moved} vs {body}"
            );
        }
        assert!((o(k, 1) - o(0, 1)).abs() < 1e-5, "the camera height stays");
    }
}

#[test]
fn bullet_time_freezes_one_pose_and_turns_the_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    tiny_scene(&scene, 1);
    let model = untrained_tiny(tmp.path());
    let out = tmp.path().join("bullet");
    ok(render(
        &model,
        &out,
        &[
            "--data",
            s(&scene),
            "--split",
            "novel_pose",
            "--camera",
            "bullet",
            "--views",
            "3",
            "--frames",
            "1:2",
            "--no-gif",
            "--reference-dirs",
        ],
    ));
    assert!(!out.join("render.gif").exists());
    let rep = report(&out);
    assert_eq!(rep["camera"], "bullet");
    assert_eq!(rep["view_dirs"], "reference");
    let frames = rep["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    assert!(frames.iter().all(|f| f["pose"] == frames[0]["pose"]));
    let o: Vec<Vec<f64>> = frames
        .iter()
        .map(|f| {
            f["camera_origin"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect()
        })
        .collect();
    assert!(o[0] != o[1] && o[1] != o[2]);
    for k in 0..3 {
        assert_eq!(png_size(&out.join(format!("frame_{k:04}.png"))), (24, 24));
    }
}

#[test]
fn bad_input_gives_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    tiny_scene(&scene, 1);
    let model = untrained_tiny(tmp.path());
    let out = tmp.path().join("o");
    let base = |extra: &[&str]| -> Output { render(&model, &out, extra) };
    fails_with(base(&[]), "pass --data DS and/or --poses");
    fails_with(base(&["--data", s(&scene), "--res", "0x5"]), "expected WxH");
    fails_with(
        base(&["--data", s(&scene), "--frames", "5:9"]),
        "selects nothing",
    );
    fails_with(
        base(&["--data", s(&scene), "--camera", "bullet", "--frame", "7"]),
        "--frame 7",
    );
    fails_with(
        base(&["--data", s(&scene), "--split", "sideways"]),
        "unknown split",
    );
    let dance = motion(tmp.path());
    fails_with(
        base(&["--poses", s(&dance), "--camera", "dataset"]),
        "--camera dataset",
    );
    fails_with(
        base(&["--poses", s(&dance), "--root-scale", "feet"]),
        "root scale",
    );
    let missing = tmp.path().join("nope.safetensors");
    fails_with(
        pma(&[
            "render",
            "--model",
            s(&missing),
            "--data",
            s(&scene),
            "--out",
            s(&out),
        ]),
        "nope.safetensors",
    );
    let garbage = tmp.path().join("garbage.npz");
    std::fs::write(&garbage, b"not an npz").unwrap();
    fails_with(base(&["--poses", s(&garbage)]), "garbage.npz");
}
