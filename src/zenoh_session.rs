//! The node on zenoh: its name and key prefix (`[node]`), its session (`[zenoh]`: an embedded peer
//! or a client of routers) and a watch on that session's connections. A leaf below everything
//! that talks on zenoh (sources, sinks, the status queryable), so none of them needs the whole
//! config.

use serde::{Deserialize, Serialize};
use zenoh::{Session, Wait};

/// Opening the session failed: the setting or the step, and zenoh's reason.
#[derive(Debug, thiserror::Error)]
#[error("zenoh: {0}")]
pub struct SessionError(pub String);

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeSettings {
    /// This node's name: the second part of every key expression.
    pub name: String,
    /// First part of every key expression.
    pub prefix: String,
}

impl Default for NodeSettings {
    fn default() -> Self {
        Self {
            name: "node".into(),
            prefix: "gdvae".into(),
        }
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSettings {
    /// "peer" (an embedded peer, no router needed) or "client" (needs a router in `connect`).
    pub mode: String,
    /// Endpoints to listen on, e.g. "tcp/0.0.0.0:7447".
    pub listen: Vec<String>,
    /// Routers or peers to connect to, e.g. "tcp/192.168.1.10:7447".
    pub connect: Vec<String>,
    /// Find peers on the LAN by UDP multicast.
    pub multicast_scouting: bool,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: true,
        }
    }
}

/// A zenoh session as configured: an embedded peer by default, or a client of routers.
pub fn open_session(z: &ZenohSettings) -> Result<Session, SessionError> {
    let mut zc = zenoh::Config::default();
    let json = |v: &Vec<String>| serde_json::to_string(v).expect("strings serialize");
    let set = |zc: &mut zenoh::Config, key: &str, value: &str| {
        zc.insert_json5(key, value)
            .map_err(|e| SessionError(format!("zenoh setting {key} = {value}: {e}")))
    };
    set(&mut zc, "mode", &format!("\"{}\"", z.mode))?;
    if !z.listen.is_empty() {
        set(&mut zc, "listen/endpoints", &json(&z.listen))?;
    }
    if !z.connect.is_empty() {
        set(&mut zc, "connect/endpoints", &json(&z.connect))?;
    }
    set(
        &mut zc,
        "scouting/multicast/enabled",
        if z.multicast_scouting { "true" } else { "false" },
    )?;
    zenoh::open(zc)
        .wait()
        .map_err(|e| SessionError(format!("opening a session: {e}")))
}

/// Watches whether the node is connected to anything it was told to connect to (`[zenoh]
/// connect`): a router outage is otherwise invisible, as zenoh accepts puts with nobody to send
/// them to. Checked at most twice a second; each change is logged once.
pub struct ConnectionWatch {
    session: Session,
    connected: bool,
    checked: std::time::Instant,
    lost_at: Option<std::time::Instant>,
}

impl ConnectionWatch {
    /// A watch when the node `publishes` on zenoh and `connect` names endpoints; None otherwise
    /// (an embedded peer with nobody configured to connect to has no outage to report).
    pub fn new(publishes: bool, z: &ZenohSettings, session: Option<&Session>) -> Option<Self> {
        let session = session.filter(|_| publishes && !z.connect.is_empty())?;
        let mut watch = Self {
            session: session.clone(),
            connected: true,
            checked: std::time::Instant::now() - std::time::Duration::from_secs(1),
            lost_at: None,
        };
        watch.connected();
        Some(watch)
    }

    /// Whether a router or peer is connected now (cached for 500 ms).
    pub fn connected(&mut self) -> bool {
        if self.checked.elapsed() < std::time::Duration::from_millis(500) {
            return self.connected;
        }
        self.checked = std::time::Instant::now();
        let info = self.session.info();
        let now = info.routers_zid().wait().next().is_some() || info.peers_zid().wait().next().is_some();
        match (self.connected, now) {
            (true, false) => {
                log::warn!("zenoh: no router or peer connected; states published now reach nobody there");
                self.lost_at = Some(std::time::Instant::now());
            }
            (false, true) => log::info!(
                "zenoh: connected again after {:.1} s; publishing reaches subscribers",
                self.lost_at.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0)
            ),
            _ => {}
        }
        self.connected = now;
        now
    }
}
