//! rmw_zenoh's graph conventions: the key a topic's data travels on, the liveliness tokens that make
//! nodes, publishers and subscriptions visible to `ros2 node list` / `ros2 topic list` (and make
//! publishers that wait for subscribers start), the QoS segment of a token, and the 33-byte
//! attachment every data sample carries.
//!
//! Formats of rmw_zenoh_cpp in Jazzy >= 0.2.4, Kilted and Rolling: `liveliness_utils.cpp` (tokens,
//! mangling, QoS), `TopicInfo` (data keys), `attachment_helpers.cpp` (attachment),
//! `rmw_publisher_data.cpp` (GID). See `../shared/reference/ros2-over-zenoh.md` for the sources.
//! Rolling and Lyrical from 0.10.5 add buffer-aware publishers (an optional field after the QoS in
//! their tokens, extra `<key>/_buf_cpu` and `<key>/_buf/<gid>` data keys); the classic fields and key
//! are unchanged, and the ROS 2 source reads the `_buf_cpu` key too.

/// The liveliness tokens' admin space.
pub const ADMIN_SPACE: &str = "@ros2_lv";

/// A ROS 2 message type: its package and name, and its RIHS01 type hash (REP-2011).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MessageType {
    pub package: &'static str,
    pub name: &'static str,
    pub hash: &'static str,
}

impl MessageType {
    /// `pkg/msg/Name`, as ROS 2 tools print it.
    pub fn ros_name(&self) -> String {
        format!("{}/msg/{}", self.package, self.name)
    }

    /// `pkg::msg::dds_::Name_`, the name in keys and tokens.
    pub fn dds_name(&self) -> String {
        format!("{}::msg::dds_::{}_", self.package, self.name)
    }
}

/// Every `/` of a name becomes `%`, so that it is one segment of a key expression.
pub fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

/// The key a topic's samples travel on: `<domain>/<topic without outer slashes>/<type>/<hash>`.
/// A ROS 2 subscriber of that type subscribes on exactly this key.
pub fn topic_key(domain: u32, topic: &str, message: &MessageType) -> String {
    format!(
        "{domain}/{}/{}/{}",
        topic.trim_matches('/'),
        message.dds_name(),
        message.hash
    )
}

/// The key expression that matches a topic's samples of a type with any type hash (a subscriber
/// that accepts whatever hash the publisher's distribution computes).
pub fn topic_key_any_hash(domain: u32, topic: &str, package: &str, name: &str) -> String {
    format!("{domain}/{}/{package}::msg::dds_::{name}_/*", topic.trim_matches('/'))
}

/// Quality of service, as far as the node sets it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub reliable: bool,
    pub transient_local: bool,
    /// History: keep last `depth`.
    pub depth: usize,
}

impl Qos {
    /// The token's QoS segment, `rel:dur:hist,depth:deadline:lifespan:liveliness,lease`, as
    /// rmw_zenoh's `qos_to_keyexpr` writes it: a field equal to rmw_zenoh's default (reliable,
    /// volatile, keep last 42, infinite durations, automatic liveliness) is left empty.
    pub fn keyexpr(&self) -> String {
        let reliability = if self.reliable { "" } else { "2" };
        let durability = if self.transient_local { "1" } else { "" };
        let depth = if self.depth == 42 {
            String::new()
        } else {
            self.depth.to_string()
        };
        format!("{reliability}:{durability}:,{depth}:,:,:,,")
    }
}

/// What an entity is in the graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    Publisher,
    Subscription,
}

impl EntityKind {
    fn tag(self) -> &'static str {
        match self {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        }
    }
}

/// One ROS 2 node as rmw_zenoh presents it: the tokens of the node and its entities.
#[derive(Debug, Clone)]
pub struct GraphNode {
    pub domain: u32,
    /// The zenoh session id as zenoh prints it.
    pub zid: String,
    /// This node's id within the session; entities take the ids after it.
    pub id: u32,
    pub enclave: String,
    /// The node's namespace, "/" or "/a/b".
    pub namespace: String,
    pub name: String,
}

impl GraphNode {
    fn prefix(&self, entity_id: u32, tag: &str) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{entity_id}/{tag}/{}/{}/{}",
            self.domain,
            self.zid,
            self.id,
            mangle(&self.enclave),
            mangle(&self.namespace),
            mangle(&self.name)
        )
    }

    /// The node's token (`ros2 node list`).
    pub fn node_token(&self) -> String {
        self.prefix(self.id, "NN")
    }

    /// A publisher's or subscription's token (`ros2 topic list`, matching).
    pub fn entity_token(
        &self,
        kind: EntityKind,
        entity_id: u32,
        topic: &str,
        message: &MessageType,
        qos: &Qos,
    ) -> String {
        self.entity_token_of(kind, entity_id, topic, &message.dds_name(), message.hash, qos)
    }

    /// The same for a type known only by its DDS name and hash (as another node advertised it).
    pub fn entity_token_of(
        &self,
        kind: EntityKind,
        entity_id: u32,
        topic: &str,
        dds_type: &str,
        hash: &str,
        qos: &Qos,
    ) -> String {
        format!(
            "{}/{}/{dds_type}/{hash}/{}",
            self.prefix(entity_id, kind.tag()),
            mangle(topic),
            qos.keyexpr()
        )
    }

    /// A name relative to the node's namespace made absolute: "pose" in "/gdvae" is "/gdvae/pose".
    pub fn resolve(&self, name: &str) -> String {
        if name.starts_with('/') {
            return name.to_string();
        }
        let namespace = self.namespace.trim_end_matches('/');
        format!("{namespace}/{name}")
    }
}

/// A publisher's GID as rmw_zenoh computes it: the XXH3-128 of its liveliness token, low half
/// first (receivers do not check it, but `ros2 topic info -v` shows it).
pub fn gid(token: &str) -> [u8; 16] {
    let hash = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
    let mut gid = [0u8; 16];
    gid[..8].copy_from_slice(&(hash as u64).to_le_bytes());
    gid[8..].copy_from_slice(&((hash >> 64) as u64).to_le_bytes());
    gid
}

/// The attachment of a data sample: sequence number and source timestamp (i64 little endian),
/// then the GID as zenoh-ext serialises a 16-byte array (its length, 0x10, then the bytes).
pub fn attachment(sequence: i64, source_timestamp_ns: i64, gid: &[u8; 16]) -> [u8; 33] {
    let mut bytes = [0u8; 33];
    bytes[..8].copy_from_slice(&sequence.to_le_bytes());
    bytes[8..16].copy_from_slice(&source_timestamp_ns.to_le_bytes());
    bytes[16] = 16;
    bytes[17..].copy_from_slice(gid);
    bytes
}

/// An attachment's fields, or why it is not one (rmw_zenoh drops samples without one).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Attachment {
    pub sequence: i64,
    pub source_timestamp_ns: i64,
    pub gid: [u8; 16],
}

pub fn parse_attachment(bytes: &[u8]) -> Result<Attachment, String> {
    if bytes.len() != 33 || bytes[16] != 16 {
        return Err(format!(
            "rmw_zenoh attachment must be 33 bytes (sequence, timestamp, 16-byte GID); got {} byte(s)",
            bytes.len()
        ));
    }
    Ok(Attachment {
        sequence: i64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")),
        source_timestamp_ns: i64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")),
        gid: bytes[17..].try_into().expect("16 bytes"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const POSE: MessageType = MessageType {
        package: "geometry_msgs",
        name: "PoseStamped",
        hash: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    };

    #[test]
    fn keys_and_tokens_follow_rmw_zenoh() {
        assert_eq!(
            topic_key(0, "/gdvae/sample/pose", &POSE),
            "0/gdvae/sample/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
        );
        let node = GraphNode {
            domain: 7,
            zid: "a1b2".into(),
            id: 0,
            enclave: "/".into(),
            namespace: "/gdvae".into(),
            name: "edge".into(),
        };
        assert_eq!(node.node_token(), "@ros2_lv/7/a1b2/0/0/NN/%/%gdvae/edge");
        let qos = Qos {
            reliable: true,
            transient_local: false,
            depth: 10,
        };
        assert_eq!(qos.keyexpr(), "::,10:,:,:,,");
        assert_eq!(
            node.entity_token(EntityKind::Publisher, 3, "/gdvae/sample/pose", &POSE, &qos),
            format!("@ros2_lv/7/a1b2/0/3/MP/%/%gdvae/edge/%gdvae%sample%pose/geometry_msgs::msg::dds_::PoseStamped_/{}/::,10:,:,:,,", POSE.hash)
        );
        assert_eq!(node.resolve("sample/pose"), "/gdvae/sample/pose");
        assert_eq!(node.resolve("/tf"), "/tf");
    }

    #[test]
    fn an_attachment_round_trips_and_a_wrong_one_is_refused() {
        let gid = gid("@ros2_lv/0/a/0/1/MP/%/%/n/%t/x/y/::,10:,:,:,,");
        let bytes = attachment(3, 1_700_000_000_000_000_000, &gid);
        assert_eq!(bytes[16], 0x10);
        let parsed = parse_attachment(&bytes).unwrap();
        assert_eq!(
            (parsed.sequence, parsed.source_timestamp_ns, parsed.gid),
            (3, 1_700_000_000_000_000_000, gid)
        );
        assert!(parse_attachment(&bytes[..32]).is_err());
        let mut keyed = bytes;
        keyed[16] = 24;
        assert!(parse_attachment(&keyed).is_err());
    }
}
