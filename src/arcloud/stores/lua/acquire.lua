-- Take every key (locks or space claims, in sorted order) or none: all-or-nothing in one step.
-- KEYS: the lock/claim keys. ARGV[1]: token, ARGV[2]: ttl in milliseconds.
-- Returns {0} when all were taken, else {i, pttl}: the first busy key (1-based) and its remaining ms.
for i, key in ipairs(KEYS) do
  if redis.call('EXISTS', key) == 1 then
    return {i, redis.call('PTTL', key)}
  end
end
for _, key in ipairs(KEYS) do
  redis.call('SET', key, ARGV[1], 'PX', ARGV[2])
end
return {0}
