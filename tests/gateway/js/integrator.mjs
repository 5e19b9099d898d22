// A SCADA integrator's session with node-opcua, driven line by line by the test:
//   node integrator.mjs opc.tcp://127.0.0.1:4840/ operator PASSWORD
// Connects as the operator, finds the machines by their type (RideMachineType) under Machines,
// subscribes to each machine's Alive, State, TiltPosition, tilt feedback and first DI, and to
// the alarms (AlarmConditionType events) on the Server object. Prints one JSON line per thing
// it sees ({"t": "value" | "event" | ...}); reads JSON commands on stdin:
//   {"do": "call", "machine": "m1", "method": "Stop"}
//   {"do": "ack", "conditionId": "ns=1;s=m1/Alarms/Estop", "eventId": "<hex>", "comment": "…"}
//   {"do": "refresh"}      ConditionRefresh on its subscription
//   {"do": "quit"}
import readline from "node:readline";
import {
  AttributeIds,
  BrowseDirection,
  ClientMonitoredItem,
  MessageSecurityMode,
  OPCUAClient,
  SecurityPolicy,
  TimestampsToReturn,
  UserTokenType,
  callConditionRefresh,
  constructEventFilter,
} from "node-opcua-client";

const [url, user, password] = process.argv.slice(2);
const NS_URI = "urn:ride-machine:gateway";
const EVENT_FIELDS = [
  "EventId", "EventType", "SourceName", "Message", "Severity", "ConditionName", "Retain",
  "ActiveState.Id", "AckedState.Id", "ClientUserId", "ConditionId",
];
const VALUES = ["Alive", "State", "TiltPosition", "Axes/tilt/PositionFeedback"];

function say(line) {
  console.log(JSON.stringify(line));
}

function plain(value) {
  if (value === null || value === undefined) return null;
  if (Buffer.isBuffer(value)) return value.toString("hex");
  if (typeof value === "object" && "text" in value) return value.text;
  if (typeof value === "object" && "toString" in value && !Array.isArray(value)) {
    return value.toString();
  }
  return value;
}

async function byType(session, ns) {
  const result = await session.browse({
    nodeId: `ns=${ns};s=gateway.Machines`,
    referenceTypeId: "Organizes",
    browseDirection: BrowseDirection.Forward,
    includeSubtypes: true,
    resultMask: 63,
  });
  const type = `ns=${ns};s=gateway.RideMachineType`;
  return result.references
    .filter((ref) => ref.typeDefinition.toString() === type)
    .map((ref) => ref.browseName.name);
}

async function firstInput(session, ns, machine) {
  const result = await session.browse(`ns=${ns};s=${machine}/IO/DI`);
  const names = (result.references || []).map((ref) => ref.browseName.name).sort();
  return names.length ? `IO/DI/${names[0]}` : null;
}

function watchValue(subscription, ns, path) {
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: `ns=${ns};s=${path}`, attributeId: AttributeIds.Value },
    { samplingInterval: 0, queueSize: 20, discardOldest: true },
    TimestampsToReturn.Both,
  );
  item.on("changed", (dv) => {
    say({ t: "value", node: path, status: dv.statusCode.name, value: plain(dv.value.value) });
  });
  item.on("err", (message) => say({ t: "item_error", node: path, message }));
}

function watchAlarms(subscription) {
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: "ns=0;i=2253", attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, queueSize: 1000, discardOldest: false,
      filter: constructEventFilter(EVENT_FIELDS) },
    TimestampsToReturn.Neither,
  );
  item.on("changed", (fields) => {
    const event = { t: "event" };
    EVENT_FIELDS.forEach((name, i) => { event[name] = plain(fields[i].value); });
    say(event);
  });
}

async function perform(session, subscription, ns, command) {
  if (command.do === "call") {
    const result = await session.call({
      objectId: `ns=${ns};s=${command.machine}`,
      methodId: `ns=${ns};s=${command.machine}/${command.method}`,
      inputArguments: [],
    });
    say({
      t: "called", machine: command.machine, method: command.method,
      status: result.statusCode.name,
      outputs: (result.outputArguments || []).map((v) => v.value),
    });
  } else if (command.do === "ack") {
    const status = await session.acknowledgeCondition(
      command.conditionId, Buffer.from(command.eventId, "hex"), command.comment || "");
    say({ t: "acked", conditionId: command.conditionId, status: status.name });
  } else if (command.do === "refresh") {
    const status = await callConditionRefresh(session, subscription.subscriptionId);
    say({ t: "refreshed", status: status.name });
  }
}

async function main() {
  const client = OPCUAClient.create({
    applicationName: "ride-machine integrator (node-opcua)",
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    endpointMustExist: false,
    keepSessionAlive: true,
    connectionStrategy: { maxRetry: 5, initialDelay: 200, maxDelay: 1000 },
  });
  await client.connect(url);
  const session = await client.createSession({
    type: UserTokenType.UserName, userName: user, password,
  });
  const ns = (await session.readNamespaceArray()).indexOf(NS_URI);
  const machines = await byType(session, ns);
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50,
    requestedLifetimeCount: 600,
    requestedMaxKeepAliveCount: 10,
    publishingEnabled: true,
  });
  watchAlarms(subscription);
  for (const machine of machines) {
    const input = await firstInput(session, ns, machine);
    for (const path of [...VALUES, ...(input ? [input] : [])]) {
      watchValue(subscription, ns, `${machine}/${path}`);
    }
  }
  say({ t: "ready", ns, machines });
  const lines = readline.createInterface({ input: process.stdin });
  for await (const line of lines) {
    const command = JSON.parse(line);
    if (command.do === "quit") break;
    try {
      await perform(session, subscription, ns, command);
    } catch (err) {
      say({ t: "failed", command, message: String(err.message || err) });
    }
  }
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  say({ t: "bye" });
}

main().catch((err) => {
  console.error(`integrator: ${err.stack || err}`);
  process.exit(1);
});
