//! An S3 server on 127.0.0.1 for tests (moto), and a TCP proxy in front of it that drops connections mid-transfer,
//! as a failing network link does. Both are owned by the test that starts them and stopped when dropped.

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The interpreter with moto: $G2R_PYTHON, else the project's .venv (which `.ci/setup` fills), else python3.
pub fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("G2R_PYTHON") {
        return p.into();
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    if venv.exists() {
        venv
    } else {
        "python3".into()
    }
}

/// A loopback port free now and not handed out before in this process: tests start servers in parallel, and two
/// of them asking the OS at once can be told the same port before either server binds it; the second server
/// then fails to start, and its test talks to the first one's, which goes away when that test ends.
fn free_port() -> u16 {
    static HANDED_OUT: Mutex<BTreeSet<u16>> = Mutex::new(BTreeSet::new());
    let mut handed_out = HANDED_OUT.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free loopback port")
            .port();
        if handed_out.insert(port) {
            return port;
        }
    }
}

/// One bare HTTP/1.1 request to `127.0.0.1:port`; the whole answer.
fn http(port: u16, method: &str, path: &str) -> std::io::Result<String> {
    let mut stream = TcpStream::connect(("127.0.0.1", port))?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )?;
    let mut answer = String::new();
    stream.read_to_string(&mut answer)?;
    Ok(answer)
}

/// moto's S3 server on a free loopback port, stopped (by its PID) when dropped.
pub struct Moto {
    child: Child,
    pub port: u16,
}

impl Moto {
    /// Start it and wait until it answers HTTP (at most a minute). A listening socket is not enough: a request
    /// sent while moto still sets itself up has been reset (CI, 2026-12-03), so readiness is a whole answer.
    pub fn start() -> Self {
        let port = free_port();
        let child = Command::new(python())
            .args([
                "-m",
                "moto.server",
                "-H",
                "127.0.0.1",
                "-p",
                &port.to_string(),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "{}: {e}; run .ci/setup (installs moto[server])",
                    python().display()
                )
            });
        let mut moto = Moto { child, port };
        let started = Instant::now();
        loop {
            if let Ok(Some(status)) = moto.child.try_wait() {
                panic!("moto exited ({status}) before answering on 127.0.0.1:{port}");
            }
            if http(port, "GET", "/").is_ok_and(|answer| answer.starts_with("HTTP/")) {
                return moto;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "moto did not answer on 127.0.0.1:{port}; is moto[server] installed in {}? (.ci/setup)",
                python().display()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// One bare HTTP request (e.g. `PUT /bucket` creates a bucket); the status code.
    pub fn request(&self, method: &str, path: &str) -> u16 {
        let answer = http(self.port, method, path)
            .unwrap_or_else(|e| panic!("{method} {path} to moto on 127.0.0.1:{}: {e}", self.port));
        answer
            .split_whitespace()
            .nth(1)
            .and_then(|code| code.parse().ok())
            .unwrap_or_else(|| panic!("moto answered {answer:?}"))
    }

    /// The S3 settings the AWS tools read, pointing at `port` (this server, or a proxy in front of it).
    pub fn env_for(port: u16) -> [(&'static str, String); 5] {
        [
            ("AWS_ENDPOINT_URL", format!("http://127.0.0.1:{port}")),
            ("AWS_ALLOW_HTTP", "true".into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ACCESS_KEY_ID", "testing".into()),
            ("AWS_SECRET_ACCESS_KEY", "testing".into()),
        ]
    }

    /// The S3 settings pointing at this server.
    pub fn env(&self) -> [(&'static str, String); 5] {
        Self::env_for(self.port)
    }
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Which way a [`CuttingProxy`] counts bytes before it cuts a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Client to server: an upload's body.
    Requests,
    /// Server to client: a download's body.
    Responses,
}

/// A TCP proxy on 127.0.0.1 in front of `127.0.0.1:target`. A connection that has carried `after_bytes` in
/// `direction` is closed at that byte, both ways, as a link that drops mid-transfer; at most `max_cuts` connections
/// are cut, later ones pass untouched (`usize::MAX`: a link that always drops).
pub struct CuttingProxy {
    pub port: u16,
    cuts: Arc<AtomicUsize>,
    stop: Arc<AtomicBool>,
    accept: Option<std::thread::JoinHandle<()>>,
}

impl CuttingProxy {
    pub fn start(target: u16, direction: Direction, after_bytes: usize, max_cuts: usize) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("binding the proxy");
        let port = listener.local_addr().expect("the proxy's address").port();
        listener
            .set_nonblocking(true)
            .expect("a non-blocking listener");
        let cuts = Arc::new(AtomicUsize::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let accept = {
            let (cuts, stop) = (cuts.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    match listener.accept() {
                        Ok((client, _)) => {
                            let Ok(server) = TcpStream::connect(("127.0.0.1", target)) else {
                                continue;
                            };
                            let _ = client.set_nonblocking(false);
                            let link = Link {
                                direction,
                                after_bytes,
                                max_cuts,
                                cuts: cuts.clone(),
                            };
                            link.spawn(client, server);
                        }
                        Err(_) => std::thread::sleep(Duration::from_millis(5)),
                    }
                }
            })
        };
        Self {
            port,
            cuts,
            stop,
            accept: Some(accept),
        }
    }

    /// Connections cut so far.
    pub fn cuts(&self) -> usize {
        self.cuts.load(Ordering::SeqCst)
    }
}

impl Drop for CuttingProxy {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(accept) = self.accept.take() {
            let _ = accept.join();
        }
    }
}

/// One proxied connection's policy.
#[derive(Clone)]
struct Link {
    direction: Direction,
    after_bytes: usize,
    max_cuts: usize,
    cuts: Arc<AtomicUsize>,
}

impl Link {
    /// Pump both ways on two threads; the counted direction may cut.
    fn spawn(self, client: TcpStream, server: TcpStream) {
        let (Ok(client2), Ok(server2)) = (client.try_clone(), server.try_clone()) else {
            return;
        };
        let (up_counted, down_counted) = match self.direction {
            Direction::Requests => (true, false),
            Direction::Responses => (false, true),
        };
        let up = self.clone();
        std::thread::spawn(move || up.pump(client, server, up_counted));
        std::thread::spawn(move || self.pump(server2, client2, down_counted));
    }

    /// Copy `from` to `to` until either closes; when `counted`, cut both at `after_bytes` if a cut is left.
    fn pump(&self, mut from: TcpStream, mut to: TcpStream, counted: bool) {
        let mut carried = 0usize;
        let mut buffer = vec![0u8; 16 * 1024];
        loop {
            let n = match from.read(&mut buffer) {
                Ok(0) | Err(_) => break,
                Ok(n) => n,
            };
            if counted && carried + n >= self.after_bytes && self.claim_cut() {
                let _ = to.write_all(&buffer[..self.after_bytes - carried]);
                let _ = to.flush();
                break;
            }
            if to.write_all(&buffer[..n]).is_err() {
                break;
            }
            carried += n;
        }
        let _ = from.shutdown(Shutdown::Both);
        let _ = to.shutdown(Shutdown::Both);
    }

    fn claim_cut(&self) -> bool {
        self.cuts
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |made| {
                (made < self.max_cuts).then_some(made + 1)
            })
            .is_ok()
    }
}
