//! A minimal Chrome DevTools Protocol client for the browser tests: Chromium started with
//! `--remote-debugging-pipe` reads commands on its fd 3 and writes answers and events on its
//! fd 4, one JSON message per NUL-terminated record. That is all a test needs to load a page,
//! run script in it, send mouse and key input and take screenshots, without a websocket or
//! browser-automation crate.

use std::fs::File;
use std::io::{BufRead as _, BufReader, Write as _};
use std::os::fd::{FromRawFd as _, RawFd};
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// Chromium's flags for a headless run in a container, with nothing fetched from outside.
const FLAGS: &[&str] = &[
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-dev-shm-usage",
    "--remote-debugging-pipe",
];

/// How long one protocol command may take.
const CALL_TIMEOUT: Duration = Duration::from_secs(60);

/// The Chromium binary: `PMA_CHROMIUM`, else Debian's `/usr/bin/chromium`.
pub fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("PMA_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let p = Path::new("/usr/bin/chromium");
    p.is_file().then(|| p.to_path_buf())
}

/// A headless Chromium with one page attached.
pub struct Browser {
    child: Child,
    to: File,
    from: mpsc::Receiver<Value>,
    next_id: u64,
    session: Option<String>,
    _profile: tempfile::TempDir,
}

fn pipe() -> (RawFd, RawFd) {
    let mut fds = [0; 2];
    // SAFETY: pipe2 writes two descriptors into the array it is given.
    let rc = unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) };
    assert_eq!(rc, 0, "pipe2: {}", std::io::Error::last_os_error());
    (fds[0], fds[1])
}

impl Browser {
    pub fn launch(exe: &Path) -> Browser {
        let profile = tempfile::tempdir().unwrap();
        let (cmd_r, cmd_w) = pipe();
        let (out_r, out_w) = pipe();
        let mut cmd = Command::new(exe);
        cmd.args(FLAGS)
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        // SAFETY: only async-signal-safe calls (fcntl, dup2) between fork and exec. The
        // descriptors are first copied above 10 so that dup2 onto 3 and 4 cannot clobber
        // one another.
        unsafe {
            cmd.pre_exec(move || {
                let a = libc::fcntl(cmd_r, libc::F_DUPFD, 10);
                let b = libc::fcntl(out_w, libc::F_DUPFD, 10);
                if a < 0 || b < 0 || libc::dup2(a, 3) < 0 || libc::dup2(b, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", exe.display()));
        // SAFETY: the browser holds its own copies now; these ends are ours alone.
        unsafe {
            libc::close(cmd_r);
            libc::close(out_w);
        }
        // SAFETY: each descriptor is owned by exactly one File from here on.
        let (to, from_file) = unsafe { (File::from_raw_fd(cmd_w), File::from_raw_fd(out_r)) };
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(from_file);
            let mut buf = Vec::new();
            loop {
                buf.clear();
                match r.read_until(0, &mut buf) {
                    Ok(0) | Err(_) => return,
                    Ok(_) => {
                        if buf.last() == Some(&0) {
                            buf.pop();
                        }
                        if let Ok(v) = serde_json::from_slice::<Value>(&buf) {
                            if tx.send(v).is_err() {
                                return;
                            }
                        }
                    }
                }
            }
        });
        Browser {
            child,
            to,
            from: rx,
            next_id: 0,
            session: None,
            _profile: profile,
        }
    }

    /// Send one command (to the attached page once there is one) and wait for its answer.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value, String> {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({ "id": id, "method": method, "params": params });
        if let Some(s) = &self.session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to
            .write_all(&bytes)
            .map_err(|e| format!("{method}: writing to the browser: {e}"))?;
        let deadline = Instant::now() + CALL_TIMEOUT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let v = self
                .from
                .recv_timeout(left)
                .map_err(|e| format!("{method}: no answer from the browser ({e})"))?;
            if v["id"].as_u64() == Some(id) {
                if let Some(err) = v.get("error") {
                    return Err(format!("{method}: {err}"));
                }
                return Ok(v["result"].clone());
            }
        }
    }

    /// Open `url` in a new page of `width`×`height` CSS pixels and attach to it.
    pub fn open(&mut self, url: &str, width: u32, height: u32) -> Result<(), String> {
        let t = self.call("Target.createTarget", json!({ "url": "about:blank" }))?;
        let target = t["targetId"].as_str().ok_or("no targetId")?.to_string();
        let a = self.call(
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
        )?;
        self.session = Some(a["sessionId"].as_str().ok_or("no sessionId")?.to_string());
        self.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        )?;
        self.call("Page.navigate", json!({ "url": url }))?;
        Ok(())
    }

    /// Evaluate `expr` in the page (promises awaited) and return its value.
    pub fn eval(&mut self, expr: &str) -> Result<Value, String> {
        let r = self.call(
            "Runtime.evaluate",
            json!({ "expression": expr, "returnByValue": true, "awaitPromise": true }),
        )?;
        if let Some(ex) = r.get("exceptionDetails") {
            return Err(format!("{expr}: {ex}"));
        }
        Ok(r["result"]["value"].clone())
    }

    /// Poll `expr` until it is truthy (its value returned) or `timeout` passes.
    pub fn wait_for(&mut self, expr: &str, timeout: Duration) -> Result<Value, String> {
        let deadline = Instant::now() + timeout;
        loop {
            let v = self.eval(expr).unwrap_or(Value::Null);
            let truthy = match &v {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64() != Some(0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return Ok(v);
            }
            if Instant::now() > deadline {
                let errors = self.eval("JSON.stringify(window.pmaView && pmaView.errors)");
                return Err(format!(
                    "waited {timeout:?} for `{expr}`; page errors: {errors:?}"
                ));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Drag with the left button from `a` to `b` (CSS pixels) in `steps` moves.
    pub fn drag(&mut self, a: (f64, f64), b: (f64, f64), steps: u32) -> Result<(), String> {
        let ev = |kind: &str, x: f64, y: f64, buttons: u32| json!({ "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 });
        self.call("Input.dispatchMouseEvent", ev("mouseMoved", a.0, a.1, 0))?;
        self.call("Input.dispatchMouseEvent", ev("mousePressed", a.0, a.1, 1))?;
        for k in 1..=steps {
            let t = k as f64 / steps as f64;
            let (x, y) = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
            self.call("Input.dispatchMouseEvent", ev("mouseMoved", x, y, 1))?;
        }
        self.call("Input.dispatchMouseEvent", ev("mouseReleased", b.0, b.1, 0))?;
        Ok(())
    }

    /// Press and release a key (`key` and `code` as the DOM names them).
    pub fn key(&mut self, key: &str, code: &str, virtual_key: u32) -> Result<(), String> {
        for kind in ["keyDown", "keyUp"] {
            self.call(
                "Input.dispatchKeyEvent",
                json!({ "type": kind, "key": key, "code": code,
                        "windowsVirtualKeyCode": virtual_key, "nativeVirtualKeyCode": virtual_key }),
            )?;
        }
        Ok(())
    }

    /// A PNG of the page as shown.
    pub fn screenshot(&mut self) -> Result<Vec<u8>, String> {
        let r = self.call("Page.captureScreenshot", json!({ "format": "png" }))?;
        base64(r["data"].as_str().ok_or("no screenshot data")?)
    }

    /// A PNG of the top `height` CSS pixels of the page, `width` wide.
    pub fn screenshot_top(&mut self, width: f64, height: f64) -> Result<Vec<u8>, String> {
        let clip = json!({ "x": 0, "y": 0, "width": width, "height": height, "scale": 1 });
        let r = self.call(
            "Page.captureScreenshot",
            json!({ "format": "png", "clip": clip }),
        )?;
        base64(r["data"].as_str().ok_or("no screenshot data")?)
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Decode standard base64 (a CDP screenshot, a `data:` URL's payload).
pub fn base64(s: &str) -> Result<Vec<u8>, String> {
    let val = |c: u8| -> Result<u32, String> {
        Ok(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return Err(format!("base64: unexpected byte {c}")),
        } as u32)
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= val(c)? << (18 - 6 * i);
        }
        let n = chunk.len() * 6 / 8;
        out.extend_from_slice(&acc.to_be_bytes()[1..1 + n]);
    }
    Ok(out)
}

#[test]
fn base64_decodes_padding_cases() {
    assert_eq!(base64("aGVsbG8=").unwrap(), b"hello");
    assert_eq!(base64("aGVsbG8h").unwrap(), b"hello!");
    assert_eq!(base64("aGk=").unwrap(), b"hi");
    assert!(base64("a*b=").is_err());
}
