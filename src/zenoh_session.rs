//! The node on zenoh: its name and key prefix (`[node]`), its session (`[zenoh]`: an embedded peer
//! or a client of routers) and a watch on that session's connections. A leaf below everything
//! that talks on zenoh (sources, sinks, the status queryable), so none of them needs the whole
//! config.

use std::path::{Path, PathBuf};

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

/// `[zenoh]`: the node's session. A zenoh configuration file (`config`, or the file
/// `ZENOH_SESSION_CONFIG_URI` names, as rmw_zenoh deployments set it) gives every zenoh setting:
/// TLS and mutual TLS, user/password authentication, access control. The four keys here, where
/// set, are applied on top of it; without a file the session is an embedded peer that scouts by
/// multicast.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSettings {
    /// A zenoh configuration file (JSON5; relative to this config's folder).
    pub config: Option<PathBuf>,
    /// "peer" (an embedded peer, no router needed) or "client" (needs a router in `connect`).
    pub mode: Option<String>,
    /// Endpoints to listen on, e.g. "tcp/0.0.0.0:7447" or "tls/0.0.0.0:7447".
    pub listen: Option<Vec<String>>,
    /// Routers or peers to connect to, e.g. "tls/base-station.local:7447".
    pub connect: Option<Vec<String>>,
    /// Find peers on the LAN by UDP multicast (default without a file: true).
    pub multicast_scouting: Option<bool>,
}

/// The environment variable rmw_zenoh's deployments set to a session's configuration file; the
/// node reads it when `[zenoh] config` is not set.
pub const SESSION_CONFIG_ENV: &str = "ZENOH_SESSION_CONFIG_URI";

impl ZenohSettings {
    /// The configuration file the session starts from: `config`, else `$ZENOH_SESSION_CONFIG_URI`.
    pub fn file(&self) -> Option<PathBuf> {
        self.config.clone().or_else(|| {
            std::env::var_os(SESSION_CONFIG_ENV)
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        })
    }

    /// Checks the keys, and the file when `config` names one (the message names the key).
    pub fn validate(&self) -> Result<(), String> {
        if let Some(mode) = self.mode.as_deref().filter(|m| !matches!(*m, "peer" | "client")) {
            return Err(format!("zenoh.mode '{mode}' must be \"peer\" or \"client\""));
        }
        let plan = plan(&session_config_from(self, self.config.as_deref()).map_err(|e| e.0)?);
        if plan.mode == "client" && plan.connect.is_empty() {
            return Err("zenoh.mode = \"client\" needs a router in zenoh.connect (or the zenoh config file's connect/endpoints)".into());
        }
        Ok(())
    }
}

/// The session's zenoh configuration: the file the settings name (or the environment's), with the
/// keys that are set applied on top.
pub fn session_config(z: &ZenohSettings) -> Result<zenoh::Config, SessionError> {
    session_config_from(z, z.file().as_deref())
}

/// [`session_config`] from a given file (None: zenoh's defaults, an embedded peer that scouts).
pub fn session_config_from(z: &ZenohSettings, file: Option<&Path>) -> Result<zenoh::Config, SessionError> {
    let mut zc = match file {
        Some(path) => zenoh::Config::from_file(path)
            .map_err(|e| SessionError(format!("zenoh configuration file {}: {e}", path.display())))?,
        None => zenoh::Config::default(),
    };
    let json = |v: &Vec<String>| serde_json::to_string(v).expect("strings serialize");
    let set = |zc: &mut zenoh::Config, key: &str, value: &str| {
        zc.insert_json5(key, value)
            .map_err(|e| SessionError(format!("zenoh setting {key} = {value}: {e}")))
    };
    let mode = z.mode.clone().or_else(|| file.is_none().then(|| "peer".into()));
    if let Some(mode) = mode {
        set(&mut zc, "mode", &format!("\"{mode}\""))?;
    }
    if let Some(listen) = &z.listen {
        set(&mut zc, "listen/endpoints", &json(listen))?;
    }
    if let Some(connect) = &z.connect {
        set(&mut zc, "connect/endpoints", &json(connect))?;
    }
    if let Some(scouting) = z.multicast_scouting.or_else(|| file.is_none().then_some(true)) {
        set(
            &mut zc,
            "scouting/multicast/enabled",
            if scouting { "true" } else { "false" },
        )?;
    }
    Ok(zc)
}

/// What a session will do, read back from its configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionPlan {
    pub mode: String,
    pub listen: Vec<String>,
    pub connect: Vec<String>,
}

/// The mode and endpoints of a configuration (endpoints given per mode are resolved for its mode).
pub fn plan(zc: &zenoh::Config) -> SessionPlan {
    let value = |key: &str| {
        zc.get_json(key)
            .ok()
            .and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
            .unwrap_or(serde_json::Value::Null)
    };
    let mode = value("mode").as_str().unwrap_or("peer").to_string();
    let endpoints = |key: &str| -> Vec<String> {
        let v = value(key);
        let list = match &v {
            serde_json::Value::Object(per_mode) => per_mode.get(&mode).cloned().unwrap_or_default(),
            other => other.clone(),
        };
        list.as_array()
            .map(|a| a.iter().filter_map(|e| e.as_str().map(str::to_string)).collect())
            .unwrap_or_default()
    };
    SessionPlan {
        listen: endpoints("listen/endpoints"),
        connect: endpoints("connect/endpoints"),
        mode,
    }
}

/// Listen endpoints that anyone on the network can reach without TLS: not on a loopback address,
/// and not `tls/` or `quic/` (whose peers must present the certificate chain the file asks for).
pub fn open_to_the_network(plan: &SessionPlan) -> Vec<String> {
    plan.listen
        .iter()
        .filter(|endpoint| {
            let (protocol, address) = endpoint.split_once('/').unwrap_or(("", endpoint));
            let host = address.rsplit_once(':').map_or(address, |(h, _)| h);
            let host = host.trim_start_matches('[').trim_end_matches(']');
            let loopback = host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback());
            !loopback && !matches!(protocol, "tls" | "quic")
        })
        .cloned()
        .collect()
}

/// A zenoh session as configured: an embedded peer by default, or a client of routers, or
/// whatever the zenoh configuration file says.
pub fn open_session(z: &ZenohSettings) -> Result<Session, SessionError> {
    let zc = session_config(z)?;
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
        let connects = session_config(z).is_ok_and(|zc| !plan(&zc).connect.is_empty());
        let session = session.filter(|_| publishes && connects)?;
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
