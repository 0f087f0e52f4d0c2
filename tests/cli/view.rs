//! `pma view` end to end: a real browser (headless Chromium over the DevTools protocol, see
//! `cdp.rs`) drives the page on a training run; raw sockets send malformed and oversized
//! requests; Ctrl-C stops the server with exit status 130.
//!
//! The browser test needs Debian's `chromium` (`.ci/run` installs it). Under `CI=true` a
//! missing browser fails the test; elsewhere the build marks it ignored (`build.rs`), so
//! `cargo test` lists it as such with the reason.

use std::io::{BufRead as _, BufReader, Read as _, Write as _};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use pma_model::render::avatar::Avatar;
use serde_json::Value;

use crate::cdp::{self, Browser};
use crate::run::{fails_with, ok, pma, pma_within, s, tiny_scene, untrained_tiny};

/// Generous bound on anything the page waits for in a debug build on a loaded machine (a
/// hang guard, not a timing check).
const LONG: Duration = Duration::from_secs(180);

/// Chromium, or `None` (with a loud message) when it is missing outside CI.
fn chromium_or_skip(test: &str) -> Option<PathBuf> {
    if let Some(p) = cdp::chromium() {
        return Some(p);
    }
    let msg = "Chromium not found (/usr/bin/chromium or PMA_CHROMIUM): install Debian's \
               `chromium` package (.ci/run does)";
    if std::env::var("CI").as_deref() == Ok("true") {
        panic!("{test}: {msg}");
    }
    eprintln!("\n*** SKIPPED {test}: {msg} ***\n");
    None
}

/// A `pma view` process serving on a free port.
struct Viewer {
    child: Child,
    port: u16,
    url: String,
    stderr: Arc<Mutex<String>>,
}

impl Viewer {
    fn start(args: &[&str]) -> Viewer {
        let mut child = Command::new(env!("CARGO_BIN_EXE_pma"))
            .arg("view")
            .args(args)
            .args(["--port", "0"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting pma view");
        let stderr = Arc::new(Mutex::new(String::new()));
        let mut err = child.stderr.take().unwrap();
        let sink = stderr.clone();
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = err.read_to_string(&mut text);
            sink.lock().unwrap().push_str(&text);
        });
        let out = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let line = rx.recv_timeout(LONG).unwrap_or_else(|_| {
            let _ = child.kill();
            let _ = child.wait();
            std::thread::sleep(Duration::from_millis(200));
            panic!(
                "pma view printed no URL; stderr:\n{}",
                stderr.lock().unwrap()
            )
        });
        let url = line
            .split_whitespace()
            .find(|w| w.starts_with("http://"))
            .unwrap_or_else(|| panic!("no URL in {line:?}"))
            .to_string();
        let port = url
            .trim_end_matches('/')
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("no port in {url}"));
        assert!(url.starts_with("http://127.0.0.1:"), "{url}: not loopback");
        Viewer {
            child,
            port,
            url,
            stderr,
        }
    }

    /// Send `raw` on a fresh connection and read the answer until the server closes it.
    fn exchange(&self, raw: &[u8]) -> Answer {
        exchange(self.port, raw)
    }

    /// A well-formed GET of `target`.
    fn get(&self, target: &str) -> Answer {
        self.exchange(
            format!(
                "GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n\r\n",
                self.port
            )
            .as_bytes(),
        )
    }

    /// SIGINT, as Ctrl-C sends; the exit status and how long the process took to end.
    fn interrupt(mut self) -> (ExitStatus, Duration) {
        let t = Instant::now();
        // SAFETY: kill(2) on our own child's pid.
        let rc = unsafe { libc::kill(self.child.id() as i32, libc::SIGINT) };
        assert_eq!(rc, 0);
        loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                let took = t.elapsed();
                // The stderr reader ends with the process.
                std::thread::sleep(Duration::from_millis(100));
                let err = self.stderr.lock().unwrap().clone();
                assert!(!err.contains("panicked"), "{err}");
                assert!(err.contains("interrupted"), "stderr after Ctrl-C:\n{err}");
                return (st, took);
            }
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "pma view did not stop after SIGINT"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

struct Answer {
    /// `None` when the server closed the connection without an HTTP answer.
    status: Option<u16>,
    head: String,
    body: Vec<u8>,
}

fn exchange(port: u16, raw: &[u8]) -> Answer {
    read_answer(send(port, raw))
}

/// Open a connection and send `raw` on it.
fn send(port: u16, raw: &[u8]) -> TcpStream {
    let mut sock = TcpStream::connect(("127.0.0.1", port)).unwrap();
    sock.set_read_timeout(Some(LONG)).unwrap();
    // A server may answer and close before reading everything (oversized heads): a failed
    // write is part of what is being tested, not a test failure.
    let _ = sock.write_all(raw);
    sock
}

/// Read the answer on `sock` until the server closes it.
fn read_answer(mut sock: TcpStream) -> Answer {
    let mut buf = Vec::new();
    let _ = sock.read_to_end(&mut buf);
    read_answer_of(buf)
}

/// The answer in the bytes a server sent.
fn read_answer_of(buf: Vec<u8>) -> Answer {
    let split = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .unwrap_or(buf.len());
    let head = String::from_utf8_lossy(&buf[..split]).into_owned();
    let status = head
        .strip_prefix("HTTP/1.1 ")
        .or_else(|| head.strip_prefix("HTTP/1.0 "))
        .and_then(|r| r.get(..3))
        .and_then(|c| c.parse().ok());
    Answer {
        status,
        head,
        body: buf.get(split + 4..).unwrap_or_default().to_vec(),
    }
}

/// Raise the density head's bias of the model at `path` to `bias` (replaced atomically, as
/// training does): a barely trained tiny model is still empty space and renders black.
fn set_density_bias(path: &Path, bias: f32) {
    let avatar = Avatar::load(path, &Device::Cpu).unwrap();
    let mut tensors = avatar.tensors();
    let b = tensors.get("sigma_linear.bias").expect("sigma_linear.bias");
    let lifted = Tensor::full(bias, b.shape(), &Device::Cpu).unwrap();
    tensors.insert("sigma_linear.bias".into(), lifted);
    Avatar::from_tensors(avatar.config().clone(), tensors, &Device::Cpu)
        .unwrap()
        .save(path)
        .unwrap();
}

/// The render canvas's pixels (RGBA).
fn canvas(b: &mut Browser) -> image::RgbaImage {
    let url = b
        .eval("document.getElementById('render').toDataURL('image/png')")
        .unwrap();
    let url = url.as_str().unwrap();
    let data = url.strip_prefix("data:image/png;base64,").unwrap();
    image::load_from_memory(&cdp::base64(data).unwrap())
        .unwrap()
        .to_rgba8()
}

/// Pixels whose colour differs by more than 2 levels in some channel.
fn differing(a: &image::RgbaImage, b: &image::RgbaImage) -> usize {
    assert_eq!(a.dimensions(), b.dimensions());
    a.pixels()
        .zip(b.pixels())
        .filter(|(p, q)| (0..3).any(|c| p.0[c].abs_diff(q.0[c]) > 2))
        .count()
}

fn lit(a: &image::RgbaImage) -> usize {
    a.pixels()
        .filter(|p| p.0[..3].iter().any(|&v| v > 10))
        .count()
}

/// The centre of the render canvas on the page (CSS pixels), where a drag starts.
fn render_centre(b: &mut Browser) -> (f64, f64) {
    let r = b
        .eval("(() => { const r = document.getElementById('render').getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()")
        .unwrap();
    let r: Vec<f64> = r
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    (r[0] + r[2] / 2.0, r[1] + r[3] / 2.0)
}

fn stats(b: &mut Browser) -> Value {
    b.eval("pmaView.lastFullStats").unwrap()
}

#[test]
#[cfg_attr(
    pma_no_chromium,
    ignore = "Chromium not found (/usr/bin/chromium or PMA_CHROMIUM): install Debian's `chromium`"
)]
fn browser_scrubs_poses_turns_the_camera_and_follows_a_run() {
    let Some(chrome) = chromium_or_skip("browser_scrubs_poses_turns_the_camera_and_follows_a_run")
    else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    let data = tiny_scene(&scene, 1);
    let cfg = tmp.path().join("run.toml");
    std::fs::write(&cfg, "preset = \"tiny\"\n[train]\neval_every = 5\n").unwrap();
    let run = tmp.path().join("run");
    ok(pma(&[
        "train",
        "--data",
        s(&data),
        "--out",
        s(&run),
        "--config",
        s(&cfg),
        "--iters",
        "10",
        "--quiet",
    ]));
    // The checkpoint the viewer shows (the run's newest complete one), changed in place.
    let model = pma_model::network::run_dir::newest_model(&run).unwrap();
    set_density_bias(&model, 5.0);

    let view = Viewer::start(&[s(&run), "--data", s(&data)]);
    let mut b = Browser::launch(&chrome);
    b.open(&view.url, 1280, 900).unwrap();

    // A dataset view: dataset camera 0, pose 0, with its ground truth and scores.
    b.wait_for("window.pmaView && pmaView.settled()", LONG)
        .unwrap();
    let st = stats(&mut b);
    assert_eq!(st["pose"], 0, "{st}");
    assert_eq!(
        (st["width"].as_u64(), st["height"].as_u64()),
        (Some(24), Some(24))
    );
    assert!(st["image"].is_u64(), "a dataset view has an image: {st}");
    for k in ["psnr", "ssim"] {
        let v = st["scores"][k].as_f64();
        assert!(v.is_some_and(f64::is_finite), "{k}: {st}");
    }
    assert!(st["rays"].as_u64().unwrap() > 0 && st["samples"].as_u64().unwrap() > 0);
    b.wait_for(
        "(() => { const g = document.getElementById('gt'); return !document.getElementById('gt-fig').hidden \
         && g.complete && g.naturalWidth === 24; })()",
        LONG,
    )
    .unwrap();
    let pose0 = canvas(&mut b);
    assert!(
        lit(&pose0) > 20,
        "the render is black: {} lit pixels",
        lit(&pose0)
    );

    // The next pose, from the keyboard on the slider.
    b.eval("document.getElementById('pose').focus()").unwrap();
    b.key("ArrowRight", "ArrowRight", 39).unwrap();
    b.wait_for(
        "pmaView.settled() && pmaView.lastFullStats.pose === 1 \
         && document.getElementById('pose-label').textContent.includes('1 /')",
        LONG,
    )
    .unwrap();
    let pose1 = canvas(&mut b);
    let d = differing(&pose0, &pose1);
    assert!(d >= 5, "poses 0 and 1 render alike ({d} pixels differ)");

    // Orbit by dragging on the render: a free camera, so no ground truth.
    let frames = b.eval("pmaView.fullFrames").unwrap().as_u64().unwrap();
    let mid = render_centre(&mut b);
    b.drag(mid, (mid.0 + 150.0, mid.1 + 20.0), 6).unwrap();
    b.wait_for(
        &format!(
            "pmaView.settled() && document.getElementById('camera').value === '-1' \
             && pmaView.fullFrames > {frames} && pmaView.lastFullStats.image === null"
        ),
        LONG,
    )
    .unwrap();
    assert_eq!(
        b.eval("document.getElementById('gt-fig').hidden").unwrap(),
        true
    );
    let turned = canvas(&mut b);
    let d = differing(&pose1, &turned);
    assert!(
        d >= 5,
        "the camera turned but the image did not change ({d} pixels)"
    );
    assert!(lit(&turned) > 20, "the turned view is black");

    // Sample culling off: exact, so the same picture (near the body hardly any sample has a
    // window of exactly 0, so the counts may be equal). Then ray culling off: every traced
    // ray runs the network.
    let both = stats(&mut b);
    assert_eq!(
        (&both["cull_rays"], &both["cull_samples"]),
        (&Value::Bool(true), &Value::Bool(true))
    );
    b.eval("document.getElementById('switch-cull_samples').click()")
        .unwrap();
    b.wait_for(
        "pmaView.settled() && pmaView.lastFullStats.cull_samples === false",
        LONG,
    )
    .unwrap();
    let rays_only = stats(&mut b);
    let unculled = canvas(&mut b);
    assert_eq!(
        differing(&turned, &unculled),
        0,
        "exact sample culling changed the image"
    );
    assert_eq!(both["rays"], rays_only["rays"]);
    assert!(
        rays_only["samples"].as_u64() >= both["samples"].as_u64(),
        "sample culling ran more samples than none: {both} vs {rays_only}"
    );
    b.eval("document.getElementById('switch-cull_rays').click()")
        .unwrap();
    b.wait_for(
        "pmaView.settled() && pmaView.lastFullStats.cull_rays === false",
        LONG,
    )
    .unwrap();
    let off = stats(&mut b);
    assert!(
        off["samples"].as_u64() > rays_only["samples"].as_u64(),
        "ray culling ran as many samples as none: {rays_only} vs {off}"
    );
    let unculled = canvas(&mut b);

    // The run's curves: 3 log rows (iterations 0, 5, 10), each with a held-out PSNR.
    b.wait_for(
        "pmaView.run && pmaView.run.loss.length >= 2 && pmaView.run.eval_psnr.length >= 2 \
         && !document.getElementById('run').hidden",
        LONG,
    )
    .unwrap();
    assert_eq!(b.eval("pmaView.run.last_iter").unwrap(), 10);

    // A new checkpoint (as `pma train` writes one) is picked up and rendered.
    assert_eq!(off["model_version"], 1);
    set_density_bias(&model, -5.0);
    b.wait_for(
        "pmaView.settled() && pmaView.lastFullStats.model_version === 2",
        LONG,
    )
    .unwrap();
    let newer = canvas(&mut b);
    assert!(
        differing(&unculled, &newer) >= 5,
        "the new checkpoint renders alike"
    );

    let errors = b.eval("pmaView.errors").unwrap();
    assert_eq!(errors, serde_json::json!([]), "page errors");
    let shot = image::load_from_memory(&b.screenshot().unwrap()).unwrap();
    assert_eq!((shot.width(), shot.height()), (1280, 900));
    drop(b);

    let (status, took) = view.interrupt();
    assert_eq!(status.code(), Some(130), "exit after Ctrl-C");
    eprintln!("pma view stopped {took:?} after SIGINT");
}

#[test]
fn malformed_and_oversized_requests_get_4xx_and_the_server_keeps_serving() {
    let tmp = tempfile::tempdir().unwrap();
    let model = untrained_tiny(tmp.path());
    let view = Viewer::start(&[s(&model)]);
    let p = view.port;
    let host = format!("Host: 127.0.0.1:{p}\r\nConnection: close\r\n");

    // A client that opened a connection and sends nothing more holds no one up.
    let mut idle = TcpStream::connect(("127.0.0.1", p)).unwrap();
    idle.write_all(b"GET / HTTP/1.1\r\n").unwrap();

    let big_header = format!(
        "GET / HTTP/1.1\r\n{host}X-Big: {}\r\n\r\n",
        "a".repeat(100_000)
    );
    let long_url = format!(
        "GET /api/render?{} HTTP/1.1\r\n{host}\r\n",
        "a".repeat(40_000)
    );
    let many_headers = format!(
        "GET / HTTP/1.1\r\n{host}{}\r\n",
        (0..200)
            .map(|i| format!("X-{i}: v\r\n"))
            .collect::<String>()
    );
    let cases: Vec<(String, Vec<u8>, u16)> = vec![
        (
            "garbage".into(),
            b"\x00\x01 not http at all\r\n\r\n".to_vec(),
            400,
        ),
        ("header of 100 kB".into(), big_header.into_bytes(), 431),
        ("URL of 40 kB".into(), long_url.into_bytes(), 431),
        ("200 headers".into(), many_headers.into_bytes(), 431),
        (
            "POST with a body".into(),
            format!("POST /api/render HTTP/1.1\r\n{host}Content-Length: 5\r\n\r\nhello")
                .into_bytes(),
            405,
        ),
        (
            "GET with a body".into(),
            format!("GET /api/info HTTP/1.1\r\n{host}Content-Length: 5\r\n\r\nhello").into_bytes(),
            413,
        ),
        (
            "HEAD".into(),
            format!("HEAD / HTTP/1.1\r\n{host}\r\n").into_bytes(),
            405,
        ),
        (
            "foreign Host".into(),
            b"GET /api/info HTTP/1.1\r\nHost: attacker.example\r\nConnection: close\r\n\r\n"
                .to_vec(),
            403,
        ),
        (
            "no Host".into(),
            b"GET /api/info HTTP/1.0\r\n\r\n".to_vec(),
            403,
        ),
    ];
    for (what, raw, want) in cases {
        let a = view.exchange(&raw);
        assert_eq!(a.status, Some(want), "{what}: {}", a.head);
    }
    for (target, want) in [
        ("/../Cargo.toml", 404),
        ("/%2e%2e/%2e%2e/etc/passwd", 404),
        ("/assets/view.js", 404),
        ("/api/render?pose=-1", 400),
        ("/api/render?pose=1", 400),
        ("/api/render?pose=abc", 400),
        ("/api/render?pose=99999999999999999999999", 400),
        ("/api/render?cam=0", 400),
        (
            "/api/render?eye=0,0,1&target=0,0,0&fov=30&w=100000&h=8",
            400,
        ),
        ("/api/render?eye=nan,0,1&target=0,0,0&fov=30", 400),
        ("/api/render?eye=0,0,0&target=0,0,0&fov=30", 400),
        ("/api/render?eye=0,-5,0&target=0,0,0&fov=30", 400),
        (
            "/api/render?eye=0,0,1&target=0,0,0&fov=30&file=/etc/passwd",
            400,
        ),
        ("/api/render?eye=0,0,1&target=0,0,0&fov=30&w=%zz", 400),
        ("/api/gt?image=0", 400),
        ("/api/gt?image=abc", 400),
        ("/api/run?x=1", 400),
    ] {
        let a = view.get(target);
        assert_eq!(a.status, Some(want), "{target}: {}", a.head);
        let body: Value = serde_json::from_slice(&a.body)
            .unwrap_or_else(|e| panic!("{target}: body is not JSON ({e})"));
        assert!(
            body["error"].as_str().is_some_and(|e| !e.is_empty()),
            "{target}: {body}"
        );
    }

    // Still serving: the page, its info, and a frame.
    let page = view.get("/");
    assert_eq!(page.status, Some(200));
    assert!(String::from_utf8_lossy(&page.body).contains("<script src=\"/view.js\">"));
    let info = view.get("/api/info");
    assert_eq!(info.status, Some(200), "{}", info.head);
    let info: Value = serde_json::from_slice(&info.body).unwrap();
    assert_eq!(info["poses"], 1);
    assert_eq!(info["pose_kind"], "rest");
    let frame = view.get(&format!(
        "/api/render?{}&fov=30&w=20&h=12",
        start_cam(&info)
    ));
    assert_eq!(frame.status, Some(200), "{}", frame.head);
    let img = image::load_from_memory(&frame.body).unwrap();
    assert_eq!((img.width(), img.height()), (20, 12));
    let stats_line = frame
        .head
        .lines()
        .find_map(|l| l.strip_prefix("x-pma-stats: "))
        .expect("x-pma-stats header");
    let st: Value = serde_json::from_str(stats_line).unwrap();
    assert_eq!(
        (st["width"].as_u64(), st["height"].as_u64()),
        (Some(20), Some(12))
    );
    drop(idle);

    let (status, took) = view.interrupt();
    assert_eq!(status.code(), Some(130));
    eprintln!("pma view stopped {took:?} after SIGINT");
}

#[test]
fn a_newer_request_stops_the_frame_in_flight() {
    let tmp = tempfile::tempdir().unwrap();
    let model = untrained_tiny(tmp.path());
    let view = Viewer::start(&[s(&model), "--chunk", "256"]);
    let info: Value = serde_json::from_slice(&view.get("/api/info").body).unwrap();
    let cam = format!("{}&fov=30", start_cam(&info));
    // Hundreds of thousands of rays without culling: minutes on a CPU, so still rendering
    // when the next request comes.
    let big = format!("/api/render?{cam}&w=1024&h=1024&cull_rays=0&cull_samples=0");
    let port = view.port;
    let get_big =
        format!("GET {big} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n");
    // Sent before the next request is, and given time to reach the render thread.
    let slow = send(port, get_big.as_bytes());
    std::thread::sleep(Duration::from_millis(300));
    let small = view.get(&format!("/api/render?{cam}&w=16&h=16"));
    assert_eq!(small.status, Some(200), "{}", small.head);
    let old = read_answer(slow);
    assert_eq!(old.status, Some(409), "{}", old.head);
    let body: Value = serde_json::from_slice(&old.body).unwrap();
    assert!(
        body["error"].as_str().unwrap().contains("superseded"),
        "{body}"
    );

    // Ctrl-C in the middle of such a frame stops the server too.
    let again = send(port, get_big.as_bytes());
    std::thread::sleep(Duration::from_millis(300));
    let (status, took) = view.interrupt();
    assert_eq!(status.code(), Some(130));
    eprintln!("pma view stopped {took:?} after SIGINT during a frame");
    // That frame's connection ends without a frame.
    let cut = read_answer(again);
    assert!(matches!(cut.status, None | Some(503)), "{}", cut.head);
}

/// The start camera's eye and target of `info` as render parameters.
fn start_cam(info: &Value) -> String {
    let v3 = |v: &Value| {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap().to_string())
            .collect::<Vec<_>>()
            .join(",")
    };
    format!(
        "eye={}&target={}",
        v3(&info["start"]["eye"]),
        v3(&info["start"]["target"])
    )
}

/// A GET of `target` that gives up after `wait` to connect and as long to read (a hang
/// shows as no answer).
fn get_within(port: u16, target: &str, wait: Duration) -> Answer {
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let Ok(mut sock) = TcpStream::connect_timeout(&addr, wait) else {
        return read_answer_of(Vec::new());
    };
    sock.set_read_timeout(Some(wait)).unwrap();
    let raw =
        format!("GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n");
    let _ = sock.write_all(raw.as_bytes());
    read_answer(sock)
}

/// What a hostile client does with its socket.
#[derive(Clone, Copy, Debug)]
enum Hostile {
    /// Connects and sends nothing (a browser's spare socket, a port scanner).
    Silent,
    /// Sends a request head a byte at a time, never finishing it.
    Trickle,
    /// Sends a whole request, keeps the connection open and sends nothing more.
    KeepAlive,
}

impl Hostile {
    fn open(self, port: u16) -> Option<TcpStream> {
        let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
        let mut sock = TcpStream::connect_timeout(&addr, Duration::from_secs(1)).ok()?;
        let head = match self {
            Hostile::Silent => String::new(),
            Hostile::Trickle => format!("GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Slow: "),
            Hostile::KeepAlive => {
                format!("GET /api/info HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n")
            }
        };
        sock.write_all(head.as_bytes()).ok()?;
        sock.set_nonblocking(true).ok()?;
        Some(sock)
    }
}

/// Whether the server still holds `sock` open (answers it may have sent are read away).
fn still_open(sock: &mut TcpStream) -> bool {
    let mut buf = [0u8; 4096];
    loop {
        match sock.read(&mut buf) {
            Ok(0) => return false,
            Ok(_) => continue,
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return true,
            Err(_) => return false,
        }
    }
}

/// What the hostile clients did.
#[derive(Debug, Default)]
struct Held {
    /// Sockets open at once, at most.
    peak: usize,
    /// Sockets the server closed, each opened again at once.
    reopened: usize,
}

/// Hold `n` sockets on `port` (a third of each kind), opening each again as soon as the
/// server closes it, until `stop`; the trickling ones send one byte a second.
fn hold(
    port: u16,
    n: usize,
    stop: Arc<std::sync::atomic::AtomicBool>,
    ready: mpsc::Sender<()>,
) -> Held {
    use std::sync::atomic::Ordering;
    let kinds = [Hostile::Silent, Hostile::Trickle, Hostile::KeepAlive];
    let mut socks: Vec<(Hostile, Option<TcpStream>)> = (0..n)
        .map(|k| {
            let kind = kinds[k % kinds.len()];
            (kind, kind.open(port))
        })
        .collect();
    let mut held = Held::default();
    let _ = ready.send(());
    let mut last_byte = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        let trickle = last_byte.elapsed() >= Duration::from_secs(1);
        if trickle {
            last_byte = Instant::now();
        }
        for (kind, sock) in socks.iter_mut() {
            if stop.load(Ordering::SeqCst) {
                break;
            }
            let open = match sock {
                Some(s) => {
                    still_open(s)
                        && !(trickle
                            && matches!(kind, Hostile::Trickle)
                            && s.write_all(b"a").is_err())
                }
                None => false,
            };
            if !open {
                held.reopened += 1;
                *sock = kind.open(port);
            }
        }
        held.peak = held
            .peak
            .max(socks.iter().filter(|(_, s)| s.is_some()).count());
        std::thread::sleep(Duration::from_millis(50));
    }
    held
}

/// Clients that hold sockets without using them (silent, trickling a request head, idle
/// after a keep-alive request), opened again as fast as the server closes them, do not keep
/// the page's own requests out. Bounded for CI: 200 sockets on 127.0.0.1 for about 10 s.
#[test]
fn idle_and_slow_clients_do_not_keep_the_page_out() {
    const SOCKETS: usize = 200;
    const HOLD: Duration = Duration::from_secs(10);
    let tmp = tempfile::tempdir().unwrap();
    let model = untrained_tiny(tmp.path());
    let view = Viewer::start(&[s(&model)]);
    let port = view.port;
    let info: Value = serde_json::from_slice(&view.get("/api/info").body).unwrap();
    let render = format!("/api/render?{}&fov=30&w=8&h=8", start_cam(&info));
    let page = [
        "/",
        "/view.js",
        "/view.css",
        "/api/info",
        "/api/run",
        render.as_str(),
    ];

    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (ready_tx, ready) = mpsc::channel();
    let holder = {
        let stop = stop.clone();
        std::thread::spawn(move || hold(port, SOCKETS, stop, ready_tx))
    };
    ready.recv().unwrap();
    let start = Instant::now();
    let (mut answered, mut failed, mut worst) = (0, Vec::new(), Duration::ZERO);
    let (mut k, mut retried) = (0, 0);
    while start.elapsed() < HOLD {
        let target = page[k % page.len()];
        k += 1;
        let t = Instant::now();
        let mut a = get_within(port, target, Duration::from_secs(5));
        if a.status.is_none() && a.head.is_empty() && t.elapsed() < Duration::from_millis(100) {
            // Closed at once without a byte: a browser sends an idempotent GET again. The
            // retry counts in the request's time, and retries must stay rare (below).
            retried += 1;
            a = get_within(port, target, Duration::from_secs(5));
        }
        let took = t.elapsed();
        worst = worst.max(took);
        if a.status == Some(200) && !a.body.is_empty() {
            answered += 1;
        } else {
            failed.push(format!("{target}: {:?} after {took:?}", a.status));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    let held = holder.join().unwrap();
    eprintln!(
        "hostile clients: {} sockets held at once ({SOCKETS} asked), {} closed by the server \
         and opened again, over {:.1} s; page requests: {answered} of {k} answered \
         ({retried} after a connection closed at once), worst {:?}",
        held.peak,
        held.reopened,
        start.elapsed().as_secs_f64(),
        worst
    );
    assert_eq!(
        held.peak, SOCKETS,
        "the hostile clients could not open their sockets"
    );
    assert!(failed.is_empty(), "page requests failed: {failed:?}");
    assert!(
        retried * 50 <= k,
        "{retried} of {k} page requests found their connection closed at once"
    );
    // A denial-of-service guarantee, not a timing: a page request takes milliseconds, and
    // both ways of being kept out cost at least a second: a SYN dropped from a full accept
    // queue is sent again after TCP's one-second retransmission timeout, and a request behind
    // the hostile sockets waits for one of their timeouts (seconds, `conns`).
    assert!(
        worst < Duration::from_secs(1),
        "slowest page request took {worst:?}: it waited for a SYN retransmission or a hostile \
         socket's timeout"
    );
    let (status, _) = view.interrupt();
    assert_eq!(status.code(), Some(130));
}

/// `/api/run` on a run directory whose `log.csv` is a FIFO answers at once with the reason,
/// every time, and leaves no thread stuck behind.
#[cfg(unix)]
#[test]
fn a_fifo_in_the_run_directory_blocks_no_request() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    std::fs::create_dir(&run).unwrap();
    let model = untrained_tiny(tmp.path());
    std::fs::copy(&model, run.join("model.safetensors")).unwrap();
    crate::run::mkfifo(&run.join("log.csv"));
    let view = Viewer::start(&[s(&run)]);
    let threads = || {
        let status = std::fs::read_to_string(format!("/proc/{}/status", view.child.id())).unwrap();
        status
            .lines()
            .find_map(|l| l.strip_prefix("Threads:"))
            .and_then(|n| n.trim().parse::<usize>().ok())
            .unwrap()
    };
    let before = threads();
    for _ in 0..6 {
        // A hang guard, not a timing: an answer takes milliseconds.
        let a = get_within(view.port, "/api/run", Duration::from_secs(30));
        assert_eq!(a.status, Some(200), "no answer: {}", a.head);
        let st: Value = serde_json::from_slice(&a.body).unwrap();
        let err = st["log_error"].as_str().unwrap_or("");
        assert!(err.contains("log.csv") && err.contains("FIFO"), "{st}");
    }
    let after = threads();
    eprintln!("pma view threads: {before} before 6 /api/run requests, {after} after");
    assert!(
        after <= before + 4,
        "{before} threads before, {after} after"
    );
    let (status, _) = view.interrupt();
    assert_eq!(status.code(), Some(130));
}

/// A request the server cannot serve is the client's error (4xx, naming what is wrong);
/// odd but valid requests are answered. No route answers a client with a 5xx.
#[test]
fn client_errors_are_4xx_on_every_route() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 1);
    let model = untrained_tiny(tmp.path());
    let view = Viewer::start(&[s(&model), "--data", s(&data)]);
    let info: Value = serde_json::from_slice(&view.get("/api/info").body).unwrap();
    let read = pma_data::dataset::ReadOptions::new(pma_data::dataset::Profile::Render);
    let images = pma_data::dataset::Dataset::read(&data, &read)
        .unwrap()
        .n_images();
    let cam = start_cam(&info);
    for (target, want, needle) in [
        (
            "/api/render?cam=0&w=8&h=8&occupancy=1".to_string(),
            400,
            "no occupancy grid".to_string(),
        ),
        (
            "/api/gt?image=abc".into(),
            400,
            format!("an integer in 0..{images}"),
        ),
        (
            format!("/api/gt?image={images}"),
            400,
            format!("past the {images} dataset images"),
        ),
        (
            "/api/gt?image=99999999999999999999999".into(),
            400,
            format!("0..{images}"),
        ),
    ] {
        let a = view.get(&target);
        let body = String::from_utf8_lossy(&a.body);
        assert_eq!(a.status, Some(want), "{target}: {body}");
        assert!(body.contains(&needle), "{target}: {body}");
        assert!(!body.contains(&usize::MAX.to_string()), "{target}: {body}");
    }
    for target in [
        "/api/render?cam=0&w=1&h=1".to_string(),
        "/api/render?cam=0&w=1&h=64&score=1".into(),
        "/api/gt?image=0".into(),
        format!("/api/render?{cam}&w=4&h=4&fov=150"),
        format!("/api/render?{cam}&w=4&h=4&fov=1"),
        format!("/api/render?{cam}&fov=30&w=4&h=4&cull_rays=0&cull_samples=0&early_stop=1"),
        format!("/api/render?{cam}&fov=30&w=4&h=4&cull_rays=0&cull_samples=0&score=1"),
        "/api/render?eye=9000,0,-9000&target=0,0,0&fov=30&w=4&h=4".into(),
        "/api/render?eye=0,0.9,0&target=0,0.9,1&fov=90&w=4&h=4".into(),
        "/api/run".into(),
    ] {
        let a = view.get(&target);
        assert_eq!(
            a.status,
            Some(200),
            "{target}: {}",
            String::from_utf8_lossy(&a.body)
        );
    }
    let (status, _) = view.interrupt();
    assert_eq!(status.code(), Some(130));
}

#[test]
fn refuses_bad_input_before_serving() {
    let tmp = tempfile::tempdir().unwrap();
    fails_with(
        pma(&["view", s(&tmp.path().join("missing.safetensors"))]),
        "no such model file or run directory",
    );
    let model = untrained_tiny(tmp.path());
    let out = pma(&["view", s(&model), "--data", s(&tmp.path().join("none.npz"))]);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    let empty_run = tmp.path().join("run");
    std::fs::create_dir(&empty_run).unwrap();
    let out = pma(&["view", s(&empty_run)]);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    fails_with(out, "the run has no checkpoint yet");
    for chunk in ["0", "1048577", "1000000000000"] {
        // Within a minute: a server that took the value would serve until stopped.
        let out = pma_within(&["view", s(&model), "--chunk", chunk, "--port", "0"], 60);
        assert_eq!(out.status.code(), Some(2), "{out:?}");
        fails_with(out, &format!("--chunk {chunk} must be in 1..=1048576"));
    }
    // A port already taken is a failure to serve (exit 1), named in the message.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port().to_string();
    let out = pma(&["view", s(&model), "--port", &port]);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    fails_with(out, "cannot listen on 127.0.0.1:");
}

/// Not a test: screenshots and timings of a running `pma view` for the docs (see
/// docs/img/SOURCE.md). `PMA_VIEW_URL` is the page, `PMA_VIEW_SHOT` the PNG to write;
/// `PMA_VIEW_SIZE` (e.g. `384x384`) picks a render size, `PMA_VIEW_DRAG=1` turns the camera
/// before the picture. Prints when the first preview and the first full frame were drawn.
#[test]
#[ignore]
fn screenshot_for_docs() {
    let url = std::env::var("PMA_VIEW_URL").expect("PMA_VIEW_URL");
    let shot = std::env::var("PMA_VIEW_SHOT").expect("PMA_VIEW_SHOT");
    let chrome = cdp::chromium().expect("Chromium");
    let mut b = Browser::launch(&chrome);
    b.open(&url, 1280, 980).unwrap();
    b.wait_for("window.pmaView && pmaView.settled()", LONG)
        .unwrap();
    let first = b
        .eval("JSON.stringify({timing: pmaView.timing, frames: pmaView.history})")
        .unwrap();
    eprintln!("first frames: {}", first.as_str().unwrap());
    if let Ok(size) = std::env::var("PMA_VIEW_SIZE") {
        let n = b.eval("pmaView.fullFrames").unwrap();
        b.eval(&format!(
            "(() => {{ const s = document.getElementById('size'); s.value = '{size}'; \
             s.dispatchEvent(new Event('change')); }})()"
        ))
        .unwrap();
        b.wait_for(
            &format!("pmaView.fullFrames > {n} && pmaView.settled()"),
            LONG,
        )
        .unwrap();
        let h = b.eval("JSON.stringify(pmaView.history.slice(-2))").unwrap();
        eprintln!("after size {size}: {}", h.as_str().unwrap());
    }
    if std::env::var("PMA_VIEW_DRAG").as_deref() == Ok("1") {
        let n = b.eval("pmaView.fullFrames").unwrap();
        let mid = render_centre(&mut b);
        b.drag(mid, (mid.0 + 90.0, mid.1 + 15.0), 8).unwrap();
        b.wait_for(
            &format!("pmaView.fullFrames > {n} && pmaView.settled()"),
            LONG,
        )
        .unwrap();
        let h = b.eval("JSON.stringify(pmaView.history.slice(-3))").unwrap();
        eprintln!("after the drag: {}", h.as_str().unwrap());
    }
    // Let the run panel's curves and the ground-truth image arrive.
    std::thread::sleep(Duration::from_millis(2500));
    let bottom = b
        .eval("Math.ceil(document.querySelector('main').getBoundingClientRect().bottom)")
        .unwrap()
        .as_f64()
        .unwrap();
    std::fs::write(&shot, b.screenshot_top(1280.0, bottom.min(980.0)).unwrap()).unwrap();
    eprintln!("wrote {shot}");
}
