--[[
vigproc.lua: run vigproc on every image darktable exports.

On each export (the `intermediate-export-image` event) the exported file is handed
to `vigproc hook`, which either

  * check:   compares the image's vignetting with the lens its EXIF names
             (forensic consistency check); nothing is written, or
  * correct: writes STEM.corrected.EXT (the export's own format) and
             STEM.vigproc.json beside the export (or into the configured folder);
             the export itself is never changed.

The result is shown in darktable (a toast), attached to the image as a tag
(vigproc|corrected, vigproc|not corrected, vigproc|check|<verdict>, vigproc|error)
and, if a report file is configured, appended to it as one JSON line per export.

Install: copy this file to ~/.config/darktable/lua/vigproc.lua and add the line
    require "vigproc"
to ~/.config/darktable/luarc; set the options in darktable's preferences (Lua
options).  See plugins/README.md.

Settings (darktable preferences; the environment variables, when set, win, which
is how headless runs with darktable-cli are configured):
  vigproc command  VIGPROC_COMMAND      path of the vigproc program (default "vigproc")
  mode             VIGPROC_MODE         off | check | correct (default check)
  output folder    VIGPROC_OUTPUT_DIR   correct mode: where outputs go (default: the export's folder)
  report file      VIGPROC_REPORT       append each JSON answer to this file (default: none)

Safety: file names are never put on a command line; they travel inside a JSON
request file.  The only command line is the vigproc program and the request
file's name, each single-quoted for /bin/sh (io.popen goes through the shell).
]]

local dt = require "darktable"

local M = {}
local SCRIPT = "vigproc"

-- ----------------------------------------------------------------- helpers

-- Quote one argument for /bin/sh: inside single quotes nothing is special
-- except the single quote itself, written as '\'' (close, escaped quote, reopen).
function M.shell_quote(s)
  return "'" .. (tostring(s):gsub("'", "'\\''")) .. "'"
end

local JSON_ESCAPES = { ['"'] = '\\"', ['\\'] = '\\\\', ['\b'] = '\\b', ['\f'] = '\\f',
                       ['\n'] = '\\n', ['\r'] = '\\r', ['\t'] = '\\t' }

-- JSON string: quotes, backslashes and control bytes escaped; other bytes are
-- passed as they are (vigproc reads non-UTF-8 bytes back as the same bytes).
function M.json_string(s)
  return '"' .. (tostring(s):gsub('[%c"\\]', function(c)
    return JSON_ESCAPES[c] or string.format("\\u%04x", c:byte())
  end)) .. '"'
end

-- Encode a value made of tables with string keys (objects), sequences (arrays),
-- strings, numbers and booleans.
function M.json_encode(v)
  local t = type(v)
  if t == "string" then return M.json_string(v) end
  if t == "number" then
    if v ~= v or v == math.huge or v == -math.huge then return "null" end
    return (math.type and math.type(v) == "integer") and tostring(v) or string.format("%.17g", v)
  end
  if t == "boolean" then return tostring(v) end
  if t == "nil" then return "null" end
  if t ~= "table" then error("cannot encode a " .. t .. " as JSON") end
  local parts = {}
  if #v > 0 or next(v) == nil then
    for i = 1, #v do parts[#parts + 1] = M.json_encode(v[i]) end
    return "[" .. table.concat(parts, ",") .. "]"
  end
  local keys = {}
  for k in pairs(v) do keys[#keys + 1] = tostring(k) end
  table.sort(keys)
  for _, k in ipairs(keys) do parts[#parts + 1] = M.json_string(k) .. ":" .. M.json_encode(v[k]) end
  return "{" .. table.concat(parts, ",") .. "}"
end

-- A small, strict JSON decoder (vigproc's answers are ASCII JSON).  null becomes nil.
function M.json_decode(s)
  local pos = 1
  local function fail(msg) error(string.format("bad JSON at byte %d: %s", pos, msg), 0) end
  local function skip() pos = s:find("[^ \t\r\n]", pos) or (#s + 1) end
  local escapes = { ['"'] = '"', ['\\'] = '\\', ['/'] = '/', b = '\b', f = '\f', n = '\n', r = '\r', t = '\t' }
  local value

  local function str()
    pos = pos + 1
    local out = {}
    while true do
      local j = s:find('["\\%c]', pos)
      if not j then fail("unterminated string") end
      out[#out + 1] = s:sub(pos, j - 1)
      pos = j
      local c = s:sub(j, j)
      if c == '"' then pos = pos + 1; return table.concat(out) end
      if c ~= "\\" then fail("control character in string") end
      local e = s:sub(pos + 1, pos + 1)
      if e == "u" then
        local hex = s:match("^%x%x%x%x", pos + 2)
        if not hex then fail("bad \\u escape") end
        local cp = tonumber(hex, 16)
        pos = pos + 6
        local lo = s:match("^\\u(%x%x%x%x)", pos)
        if cp >= 0xD800 and cp <= 0xDBFF and lo and tonumber(lo, 16) >= 0xDC00 and tonumber(lo, 16) <= 0xDFFF then
          cp = 0x10000 + (cp - 0xD800) * 0x400 + (tonumber(lo, 16) - 0xDC00)
          pos = pos + 6
        end
        out[#out + 1] = utf8.char(cp)
      elseif escapes[e] then
        out[#out + 1] = escapes[e]
        pos = pos + 2
      else
        fail("bad escape")
      end
    end
  end

  local function composite(close, depth, item)
    local t, n = {}, 0
    pos = pos + 1
    skip()
    if s:sub(pos, pos) == close then pos = pos + 1; return t end
    while true do
      n = n + 1
      item(t, n, depth)
      skip()
      local c = s:sub(pos, pos)
      pos = pos + 1
      if c == close then return t end
      if c ~= "," then fail("expected ',' or '" .. close .. "'") end
      skip()
    end
  end

  value = function(depth)
    if depth > 64 then fail("nested too deeply") end
    skip()
    local c = s:sub(pos, pos)
    if c == "{" then
      return composite("}", depth, function(t, _, d)
        skip()
        if s:sub(pos, pos) ~= '"' then fail("expected a key") end
        local k = str()
        skip()
        if s:sub(pos, pos) ~= ":" then fail("expected ':'") end
        pos = pos + 1
        t[k] = value(d + 1)
      end)
    elseif c == "[" then
      return composite("]", depth, function(t, n, d) t[n] = value(d + 1) end)
    elseif c == '"' then
      return str()
    end
    for word, v in pairs({ ["true"] = true, ["false"] = false }) do
      if s:sub(pos, pos + #word - 1) == word then pos = pos + #word; return v end
    end
    if s:sub(pos, pos + 3) == "null" then pos = pos + 4; return nil end
    local num = s:match("^-?%d+%.?%d*[eE]?[-+]?%d*", pos)
    if not num or not tonumber(num) then fail("unexpected character") end
    pos = pos + #num
    return tonumber(num)
  end

  local v = value(0)
  skip()
  if pos <= #s then fail("trailing characters") end
  return v
end

local function basename(path)
  return (tostring(path):match("([^/]*)$"))
end

local function dirname(path)
  local d = tostring(path):match("^(.*)/[^/]*$")
  if d == nil then return "." end
  return d == "" and "/" or d
end

-- ----------------------------------------------------------------- settings

local function pref(name, kind, default)
  local ok, v = pcall(dt.preferences.read, SCRIPT, name, kind)
  if not ok or v == nil or v == "" then return default end
  return v
end

function M.settings()
  local env = os.getenv
  local s = {
    command = env("VIGPROC_COMMAND") or pref("command", "string", "vigproc"),
    mode = env("VIGPROC_MODE") or pref("mode", "enum", "check"),
    output_dir = env("VIGPROC_OUTPUT_DIR") or pref("output_dir", "string", ""),
    report = env("VIGPROC_REPORT") or pref("report", "string", ""),
  }
  if s.mode ~= "off" and s.mode ~= "check" and s.mode ~= "correct" then
    s.mode = "check"
  end
  return s
end

-- ----------------------------------------------------------------- running vigproc

-- The lens darktable's own image record names, as a hook request's "lens" (nil when
-- darktable knows no lens). An export drops maker notes (Canon's name the lens there),
-- so the export's EXIF alone may say "unknown lens" where darktable knows it.
function M.lens_of(image)
  if image == nil then return nil end
  local ok, lens = pcall(function() return image.exif_lens end)
  if not ok or type(lens) ~= "string" or lens == "" then return nil end
  local t = { lens = lens }
  local fields = { make = "exif_maker", model = "exif_model", focal_mm = "exif_focal_length",
                   fnumber = "exif_aperture" }
  for key, field in pairs(fields) do
    local got, v = pcall(function() return image[field] end)
    if got and ((type(v) == "string" and v ~= "") or (type(v) == "number" and v > 0)) then t[key] = v end
  end
  return t
end

-- Build the request for one exported file (pure: tested without darktable).
function M.request(settings, filename, image)
  local lens = M.lens_of(image)
  local entry = filename
  if lens ~= nil then entry = { path = filename, lens = lens } end
  local req = { mode = settings.mode, files = { entry } }
  if settings.mode == "correct" then
    req.output_dir = settings.output_dir ~= "" and settings.output_dir or dirname(filename)
  end
  return req
end

-- The command line: program and request file, both quoted; nothing else.
function M.command(settings, request_file)
  return M.shell_quote(settings.command) .. " hook --request " .. M.shell_quote(request_file)
end

-- Run vigproc on one file; returns the decoded answer (or nil) and a message.
function M.run(settings, filename, image)
  local tmp = os.tmpname()
  local f = assert(io.open(tmp, "wb"))
  f:write(M.json_encode(M.request(settings, filename, image)))
  f:close()
  local pipe = io.popen(M.command(settings, tmp), "r")
  local out = pipe and pipe:read("a") or ""
  local code
  if pipe then code = select(3, pipe:close()) end
  os.remove(tmp)
  if settings.report ~= "" and out ~= "" then
    local r = io.open(settings.report, "ab")
    if r then r:write((out:gsub("\n*$", "")), "\n"); r:close() end
  end
  local ok, answer = pcall(M.json_decode, out)
  if not ok or type(answer) ~= "table" then
    return nil, string.format("vigproc gave no answer (exit code %s); is '%s' the vigproc program?",
                              tostring(code), settings.command)
  end
  if answer.error then return answer, "vigproc: " .. tostring(answer.error) end
  local r = answer.results and answer.results[1]
  if not r then return answer, "vigproc: empty answer" end
  if r.status ~= "ok" then return answer, "vigproc: " .. tostring(r.error) end
  return answer, "vigproc: " .. basename(filename) .. ": " .. tostring(r.summary)
end

-- The tag that records the result on the image.
function M.tag_for(answer)
  local r = answer and answer.results and answer.results[1]
  if not r or r.status ~= "ok" then return "vigproc|error" end
  if r.mode == "check" then
    return "vigproc|check|" .. tostring((r.verdict or {}).verdict or "no verdict")
  end
  if r.mode == "correct" then return r.applied and "vigproc|corrected" or "vigproc|not corrected" end
  return "vigproc|estimated"
end

local function report(image, answer, message)
  pcall(dt.print, message)
  pcall(dt.print_log, message)
  if image ~= nil then
    pcall(function()
      dt.tags.attach(dt.tags.create(M.tag_for(answer)), image)
    end)
  end
end

function M.on_export(_, image, filename, _, _)
  local settings = M.settings()
  if settings.mode == "off" then return end
  local ok, answer, message = pcall(M.run, settings, filename, image)
  if not ok then answer, message = nil, "vigproc failed: " .. tostring(answer) end
  report(image, answer, message)
end

-- ----------------------------------------------------------------- registration

if dt.register_event ~= nil then
  -- darktable-cli has no preferences dialog (registering one there blocks it)
  if dt.configuration.has_gui then pcall(function()
    dt.preferences.register(SCRIPT, "report", "string", "vigproc: report file",
      "append vigproc's JSON answer for each export to this file (empty: none)", "")
    dt.preferences.register(SCRIPT, "output_dir", "string", "vigproc: output folder",
      "correct mode: folder for the corrected images (empty: the export's folder)", "")
    dt.preferences.register(SCRIPT, "command", "string", "vigproc: program",
      "path of the vigproc program", "vigproc")
    dt.preferences.register(SCRIPT, "mode", "enum", "vigproc: on export",
      "check: vignetting vs the lens in EXIF; correct: also write a corrected TIFF", "check",
      "off", "check", "correct")
  end) end
  dt.register_event(SCRIPT, "intermediate-export-image", M.on_export)
end

return M
