// node-opcua as a second, independent OPC UA client of the GWC gateway (tests/e2e/test_opcua.py).
// Commands come one JSON object a line on stdin; replies and notifications go one JSON object a line
// on stdout. Anything else node-opcua says goes to stderr.
"use strict";
const readline = require("readline");
// node-opcua writes its warnings with console.log: stdout is this script's protocol, so they go to stderr.
const toStderr = (...args) => process.stderr.write(args.map(String).join(" ") + "\n");
console.log = console.info = console.warn = console.debug = toStderr;
const {
    OPCUAClient,
    AttributeIds,
    TimestampsToReturn,
    makeBrowsePath,
    ClientSubscription,
    ClientMonitoredItem,
} = require("node-opcua-client");

let client = null;
let session = null;
let aliases = {}; // alias -> namespace index
const say = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const iso = (d) => (d ? d.toISOString() : null);
const plain = (v) => {
    if (v === null || v === undefined) return null;
    if (typeof v === "bigint") return Number(v);
    if (Array.isArray(v) && v.length === 2 && typeof v[0] === "number") return v[0] * 2 ** 32 + v[1]; // node-opcua's Int64
    if (typeof v === "object" && "text" in v) return v.text; // LocalizedText
    if (typeof v === "object" && typeof v.toString === "function") return v.toString();
    return v;
};
const dataValue = (dv) => ({
    status: dv.statusCode.name,
    value: plain(dv.value ? dv.value.value : null),
    sourceTimestamp: iso(dv.sourceTimestamp),
    serverTimestamp: iso(dv.serverTimestamp),
});
const path = (text) => text.replace(/([a-z]+):/g, (m, a) => (a in aliases ? `${aliases[a]}:` : m));

async function connect(cmd) {
    client = OPCUAClient.create({
        endpointMustExist: false,
        keepSessionAlive: true,
        requestedSessionTimeout: 60000,
        connectionStrategy: { maxRetry: -1, initialDelay: 200, maxDelay: 1000 },
    });
    for (const ev of ["connection_lost", "connection_reestablished", "after_reconnection", "start_reconnection"]) {
        client.on(ev, () => say({ event: ev, at: new Date().toISOString() }));
    }
    await client.connect(cmd.endpoint);
    session = await client.createSession();
    const namespaces = await session.readNamespaceArray();
    aliases = {};
    for (const [alias, uri] of Object.entries(cmd.aliases || {})) aliases[alias] = namespaces.indexOf(uri);
    return { namespaces, aliases };
}

async function browse(cmd) {
    const results = [];
    for (const text of cmd.paths) {
        const found = await session.translateBrowsePath(makeBrowsePath("RootFolder", path(text)));
        const target = found.targets && found.targets.length ? found.targets[0].targetId.toString() : null;
        const entry = { path: text, status: found.statusCode.name, nodeId: target };
        if (target) {
            const [dv] = await session.read([{ nodeId: target, attributeId: AttributeIds.Value }], 0);
            Object.assign(entry, dataValue(dv));
        }
        results.push(entry);
    }
    return { results };
}

async function read(cmd) {
    const dvs = await session.read(cmd.nodeIds.map((nodeId) => ({ nodeId, attributeId: AttributeIds.Value })), 0);
    return { results: dvs.map((dv, i) => ({ nodeId: cmd.nodeIds[i], ...dataValue(dv) })) };
}

async function subscribe(cmd) {
    const sub = ClientSubscription.create(session, {
        requestedPublishingInterval: 50,
        requestedLifetimeCount: 600,
        requestedMaxKeepAliveCount: 10,
        maxNotificationsPerPublish: 0,
        publishingEnabled: true,
    });
    for (const nodeId of cmd.nodeIds) {
        const item = ClientMonitoredItem.create(
            sub,
            { nodeId, attributeId: AttributeIds.Value },
            { samplingInterval: 0, discardOldest: true, queueSize: 20 },
            TimestampsToReturn.Both,
        );
        item.on("changed", (dv) => say({ event: "change", nodeId, at: new Date().toISOString(), ...dataValue(dv) }));
    }
    return {};
}

const commands = { connect, browse, read, subscribe };
const lines = readline.createInterface({ input: process.stdin });
lines.on("line", async (line) => {
    const cmd = JSON.parse(line);
    if (cmd.cmd === "close") {
        try {
            if (session) await session.close();
            if (client) await client.disconnect();
        } finally {
            say({ reply: "close" });
            process.exit(0);
        }
    }
    try {
        say({ reply: cmd.cmd, ...(await commands[cmd.cmd](cmd)) });
    } catch (err) {
        say({ reply: cmd.cmd, error: String(err && err.message ? err.message : err) });
    }
});
lines.on("close", () => process.exit(0));
