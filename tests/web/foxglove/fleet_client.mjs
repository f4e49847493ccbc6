// A Foxglove WebSocket client of the live fleet, with Foxglove's own libraries: @foxglove/ws-protocol's
// FoxgloveClient (on the `ws` package's WebSocket), @foxglove/rosmsg to parse each channel's ros1msg
// schema and @foxglove/rosmsg-serialization to decode and encode ROS 1 messages.
//
//   node fleet_client.mjs URL ROBOT GOAL_CELL TIMEOUT_MS
//
// Subscribes to every robot's /RobotN/pose, /fleet/state and /map; once ROBOT's poses arrive it
// advertises /fleet/goal (fleet/RobotGoal, ros1) and publishes {robot: ROBOT, cell: GOAL_CELL}; it ends
// when the fleet state shows ROBOT on its way to that goal and its pose has moved 0.3 m, printing one
// JSON line of what it saw. Exits 1 (with what it saw) when that does not happen within TIMEOUT_MS.
import wsProtocol from "@foxglove/ws-protocol";
import rosmsg from "@foxglove/rosmsg";
import serialization from "@foxglove/rosmsg-serialization";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
const { parse } = rosmsg;
const { MessageReader, MessageWriter } = serialization;

const [url, robot, goalArg, timeoutArg] = process.argv.slice(2);
const goal = Number(goalArg);
const ROBOT_GOAL = "string robot\nint32 cell\n";
const seen = { serverInfo: null, channels: {}, poses: {}, statuses: [], mapSize: null, goalSent: false,
               goalTaken: false, moved: 0, firstPose: null, lastPose: null, schemaOfPose: null };
const readers = new Map();      // subscription id -> { topic, reader }
const client = new FoxgloveClient({ ws: new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
let goalChannel = null;

function finish(code) {
  console.log(JSON.stringify(seen));
  client.close();
  process.exit(code);
}
setTimeout(() => finish(1), Number(timeoutArg));

client.on("error", (e) => { seen.statuses.push(`error: ${e}`); });
client.on("close", () => { seen.statuses.push("closed"); finish(1); });
client.on("serverInfo", (info) => { seen.serverInfo = info; });
client.on("status", (s) => { seen.statuses.push(s); });
client.on("advertise", (channels) => {
  for (const ch of channels) {
    seen.channels[ch.topic] = { encoding: ch.encoding, schemaName: ch.schemaName, schemaEncoding: ch.schemaEncoding };
    const wanted = /^\/Robot\d+\/pose$/.test(ch.topic) || ch.topic === "/fleet/state" || ch.topic === "/map";
    if (!wanted) continue;
    if (ch.encoding !== "ros1" || ch.schemaEncoding !== "ros1msg") throw new Error(`${ch.topic}: not ros1`);
    const reader = new MessageReader(parse(ch.schema, { ros2: false }));
    readers.set(client.subscribe(ch.id), { topic: ch.topic, reader });
    if (ch.topic === `/${robot}/pose`) seen.schemaOfPose = ch.schemaName;
  }
});

function dist(a, b) { return Math.hypot(a.x - b.x, a.y - b.y); }

client.on("message", ({ subscriptionId, data }) => {
  const sub = readers.get(subscriptionId);
  if (!sub) return;
  const msg = sub.reader.readMessage(data);
  if (sub.topic === "/map") {
    seen.mapSize = [msg.info.width, msg.info.height, msg.data.length, msg.header.frame_id];
  } else if (sub.topic === "/fleet/state") {
    const r = msg.robots.find((x) => x.robot === robot);
    if (seen.goalSent && r && r.goal === goal && r.path.length > 0) seen.goalTaken = true;
  } else {
    const who = sub.topic.split("/")[1];
    seen.poses[who] = (seen.poses[who] || 0) + 1;
    if (who !== robot) return;
    const p = msg.pose.position;
    if (msg.header.frame_id !== "map") throw new Error(`pose in frame ${msg.header.frame_id}`);
    seen.lastPose = { x: p.x, y: p.y };
    if (seen.poses[robot] === 3) {
      seen.firstPose = { x: p.x, y: p.y };
      goalChannel = client.advertise({ topic: "/fleet/goal", encoding: "ros1", schemaName: "fleet/RobotGoal",
                                       schema: ROBOT_GOAL, schemaEncoding: "ros1msg" });
      const bytes = new MessageWriter(parse(ROBOT_GOAL, { ros2: false })).writeMessage({ robot, cell: goal });
      client.sendMessage(goalChannel, bytes);
      seen.goalSent = true;
    }
    if (seen.firstPose) seen.moved = dist(seen.firstPose, seen.lastPose);
    if (seen.goalTaken && seen.moved > 0.3 && seen.mapSize) finish(0);
  }
});
