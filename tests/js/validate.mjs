// Validate replies captured from a machine daemon against the checked-in JSON Schema.
//
//   node validate.mjs SCHEMA_DIR CAPTURES_JSON
//
// CAPTURES_JSON is a list of {"key": "<key under machine/<id>>", "payload": <reply as JSON>}.
// Each key is looked up in SCHEMA_DIR/keys.json (the key space as data); a payload with
// "success": false is checked against the error reply model, any other against the key's
// reply model. Prints one JSON summary line; exits 1 if any payload does not validate.
import fs from "node:fs";
import path from "node:path";
import Ajv2020 from "ajv/dist/2020.js";
import addFormats from "ajv-formats";

const [schemaDir, capturesFile] = process.argv.slice(2);
if (!schemaDir || !capturesFile) {
  console.error("usage: node validate.mjs SCHEMA_DIR CAPTURES_JSON");
  process.exit(2);
}
const read = (file) => JSON.parse(fs.readFileSync(file, "utf8"));

// strict: false only lets pydantic's OpenAPI-style "discriminator" annotation through.
const ajv = new Ajv2020({ allErrors: true, strict: false });
addFormats(ajv);
for (const file of fs.readdirSync(schemaDir).sort()) {
  if (file.endsWith(".json") && file !== "keys.json") {
    ajv.addSchema(read(path.join(schemaDir, file)));
  }
}
const keys = read(path.join(schemaDir, "keys.json"));

function specOf(key) {
  const parts = key.split("/");
  return keys.keys.find((spec) => {
    const pattern = spec.key.split("/");
    return (
      pattern.length === parts.length &&
      pattern.every((p, i) => p === parts[i] || (p.startsWith("<") && p.endsWith(">")))
    );
  });
}

const failures = [];
const checked = {};
for (const { key, payload } of read(capturesFile)) {
  const spec = specOf(key);
  if (!spec || !spec.reply) {
    failures.push({ key, errors: ["no reply model for this key in keys.json"] });
    continue;
  }
  const model = payload && payload.success === false ? keys.error_reply : spec.reply;
  const validate = ajv.getSchema(`${model}.json`);
  if (!validate) {
    failures.push({ key, errors: [`no schema ${model}.json`] });
    continue;
  }
  if (validate(payload)) {
    checked[model] = (checked[model] || 0) + 1;
  } else {
    const errors = validate.errors.map((e) => `${e.instancePath || "/"} ${e.message}`);
    failures.push({ key, model, errors });
  }
}
console.log(JSON.stringify({ checked, failures }));
process.exit(failures.length ? 1 : 0);
