// An OPC UA client nobody here wrote (node-opcua) against `rider gateway`:
//   node opcua_check.mjs opc.tcp://127.0.0.1:4840/ operator PASSWORD m1
// Browses Objects -> Machines -> <machine>, reads and subscribes to State, calls Stop, Home
// and a Start that the machine refuses, and prints one JSON line of what it saw.
import {
  AttributeIds,
  ClientMonitoredItem,
  DataType,
  MessageSecurityMode,
  OPCUAClient,
  SecurityPolicy,
  StatusCodes,
  TimestampsToReturn,
  UserTokenType,
} from "node-opcua-client";

const [url, user, password, machine] = process.argv.slice(2);
const NS_URI = "urn:ride-machine:gateway";

async function callMethod(session, ns, method, inputArguments) {
  const result = await session.call({
    objectId: `ns=${ns};s=${machine}`,
    methodId: `ns=${ns};s=${machine}/${method}`,
    inputArguments,
  });
  return {
    status: result.statusCode.name,
    good: result.statusCode.isGood(),
    outputs: (result.outputArguments || []).map((v) => v.value),
  };
}

async function main() {
  const client = OPCUAClient.create({
    applicationName: "ride-machine node check",
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 2, initialDelay: 200, maxDelay: 1000 },
  });
  const out = {};
  await client.connect(url);
  try {
    const session = await client.createSession({
      type: UserTokenType.UserName,
      userName: user,
      password,
    });
    try {
      const nsArray = await session.readNamespaceArray();
      const ns = nsArray.indexOf(NS_URI);
      out.namespace = ns;
      // Browse by names, as a SCADA engineer would click through.
      const path = await session.translateBrowsePath({
        startingNode: "ns=0;i=85", // Objects
        relativePath: {
          elements: [
            { referenceTypeId: "ns=0;i=33", isInverse: false, includeSubtypes: true,
              targetName: { namespaceIndex: ns, name: "Machines" } },
            { referenceTypeId: "ns=0;i=33", isInverse: false, includeSubtypes: true,
              targetName: { namespaceIndex: ns, name: machine } },
            { referenceTypeId: "ns=0;i=33", isInverse: false, includeSubtypes: true,
              targetName: { namespaceIndex: ns, name: "State" } },
          ],
        },
      });
      out.browse = path.statusCode.name;
      const stateId = path.targets[0].targetId.toString();
      out.stateNode = stateId;
      const read = await session.read({ nodeId: stateId, attributeId: AttributeIds.Value });
      out.read = { status: read.statusCode.name, value: read.value.value };

      const subscription = await session.createSubscription2({
        requestedPublishingInterval: 50,
        requestedLifetimeCount: 100,
        requestedMaxKeepAliveCount: 10,
        publishingEnabled: true,
      });
      const seen = [];
      const item = ClientMonitoredItem.create(
        subscription,
        { nodeId: stateId, attributeId: AttributeIds.Value },
        { samplingInterval: 0, queueSize: 10, discardOldest: true },
        TimestampsToReturn.Both,
      );
      const homing = new Promise((resolve, reject) => {
        const timer = setTimeout(() => reject(new Error(`no HOMING change: ${seen}`)), 15000);
        item.on("changed", (dv) => {
          seen.push(dv.value.value);
          if (dv.value.value === "HOMING") {
            clearTimeout(timer);
            // What was seen up to HOMING, copied now: the Stop below changes the state again,
            // and a busy host may deliver that change before the line is printed.
            resolve({ at: dv.sourceTimestamp, seen: [...seen] });
          }
        });
      });
      out.stop = await callMethod(session, ns, "Stop", []);
      out.home = await callMethod(session, ns, "Home", []);
      const homed = await homing;
      out.homingSource = homed.at.toISOString();
      out.changes = homed.seen;
      out.start = await callMethod(session, ns, "Start", [
        { dataType: DataType.String, value: "" },
      ]);
      out.stopAgain = await callMethod(session, ns, "Stop", []);
      await subscription.terminate();
    } finally {
      await session.close();
    }
  } finally {
    await client.disconnect();
  }
  console.log(JSON.stringify(out));
}

main().catch((err) => {
  console.error(`opcua_check: ${err.stack || err}`);
  process.exit(1);
});
