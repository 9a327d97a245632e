//! ROS 2 on the wire, as rmw_zenoh carries it: graph conventions (keys, liveliness tokens, QoS,
//! attachments; `graph`) and the messages the node writes (`msg`). Shared by the ROS 2 sink
//! (`publish::ros2`) and the ROS 2 source (`sources::zenoh` with `kind = "ros2"`); the CDR reader
//! for incoming messages is `sources::ros2`.

pub mod graph;
pub mod msg;
mod settings;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use zenoh::{Session, Wait};

use graph::GraphNode;
pub use settings::Ros2Settings;

/// The node in one ROS 2 domain: its liveliness token (`ros2 node list`) and the ids of its
/// entities, handed out as rmw_zenoh does (the node first, then each publisher and subscription).
/// The token is withdrawn when the last user drops it.
pub struct Participant {
    node: GraphNode,
    session: Session,
    next_id: AtomicU32,
    _token: zenoh::liveliness::LivelinessToken,
}

impl Participant {
    pub fn node(&self) -> &GraphNode {
        &self.node
    }

    pub fn session(&self) -> &Session {
        &self.session
    }

    /// A fresh entity id within the session.
    pub fn next_id(&self) -> u32 {
        self.next_id.fetch_add(1, Ordering::Relaxed)
    }
}

/// The node's participants, one per ROS 2 domain it publishes or subscribes in, named by
/// `[publish.ros2]` (namespace, node name, enclave) whether or not it publishes.
pub struct Participants {
    session: Session,
    settings: Ros2Settings,
    joined: Mutex<HashMap<u32, Arc<Participant>>>,
}

impl Participants {
    pub fn new(session: Session, settings: &Ros2Settings) -> Self {
        Self {
            session,
            settings: settings.clone(),
            joined: Mutex::default(),
        }
    }

    /// The node in `domain`, its token declared on first use.
    pub fn join(&self, domain: u32) -> Result<Arc<Participant>, zenoh::Error> {
        let mut joined = self.joined.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(participant) = joined.get(&domain) {
            return Ok(participant.clone());
        }
        let node = GraphNode {
            domain,
            zid: self.session.zid().to_string(),
            id: 0,
            enclave: self.settings.enclave.clone(),
            namespace: self.settings.namespace.clone(),
            name: self.settings.node_name.clone(),
        };
        let token = self.session.liveliness().declare_token(node.node_token()).wait()?;
        let participant = Arc::new(Participant {
            node,
            session: self.session.clone(),
            next_id: AtomicU32::new(1),
            _token: token,
        });
        joined.insert(domain, participant.clone());
        Ok(participant)
    }
}
