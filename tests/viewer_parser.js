// Runs the viewers' own parseJsonSchema (extracted from the npm package by viewer_parser.py) on
// cases read from the JSON file argv[2]: {parser, base64, cases: [{name, schema, messages}]}.
// Prints one result per case: {ok, datatypes (type -> fields), messages} (messages after the parser's
// postprocessValue, bytes as {bytes: n}) or {ok: false, error}.
"use strict";
const fs = require("fs");

const input = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
const source = fs.readFileSync(input.parser, "utf8");
const parseJsonSchema = new Function("base64", `${source}\nreturn parseJsonSchema;`)(
  require(input.base64),
);

const results = input.cases.map(({ name, schema, messages }) => {
  try {
    const { datatypes, postprocessValue } = parseJsonSchema(schema, name);
    return {
      ok: true,
      datatypes: Object.fromEntries([...datatypes].map(([type, { definitions }]) => [type, definitions])),
      messages: messages.map((message) => postprocessValue(message)),
    };
  } catch (error) {
    return { ok: false, error: String(error.message) };
  }
});
const bytesAsLength = (key, value) =>
  value instanceof Uint8Array ? { bytes: value.byteLength } : value;
process.stdout.write(JSON.stringify(results, bytesAsLength));
